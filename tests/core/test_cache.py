import torch

from torchiid.core.cache import input_key


def test_same_tensor_unmodified_matches():
    x = torch.rand(4, 5)
    assert input_key(x, 1.0, None, "a") == input_key(x, 1.0, None, "a")
    assert input_key(x, 1.0) != input_key(x, 2.0)
    assert input_key(x) != input_key(x, None)


def test_equal_or_recycled_storage_does_not_match():
    x = torch.rand(4, 4)
    key = input_key(x)
    # same values, same storage address, other tensor objects: never the same inputs
    assert key != input_key(x.clone())
    assert key != input_key(x.view(4, 4))
    assert key != input_key(x.t())  # same data_ptr and shape, other strides
    # a key keeps its tensor alive, so its memory cannot be handed to a new tensor
    ptr = x.data_ptr()
    del x
    y = torch.rand(4, 4)
    assert y.data_ptr() != ptr or key != input_key(y)


def test_in_place_change_and_inference_tensors_never_match():
    x = torch.rand(3)
    key = input_key(x)
    x.mul_(2)
    assert key != input_key(x)
    with torch.inference_mode():
        y = torch.rand(3)
        assert input_key(y) != input_key(y)  # no version counter: never reused
