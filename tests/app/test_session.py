"""Opening a photo in the app: the layers it keeps, the progress it reports, its checks."""

from __future__ import annotations

import pytest
import torch
from PIL import Image

pytest.importorskip("gradio")

from torchiid.app.session import open_photo  # noqa: E402
from torchiid.core.exceptions import ImageError, MemoryLimitError  # noqa: E402
from torchiid.params import Parameters  # noqa: E402

ONE = Parameters().replace(iterations=1)


def test_the_session_keeps_the_exact_layers_and_a_preview_that_reconstructs_the_photo(
    chelsea_session,
):
    s = chelsea_session
    assert s.name == "chelsea.png" and s.stem == "chelsea"
    full, preview = s.full, s.preview
    assert full.image.shape == (1, 3, 150, 200) and full.shading.shape == (1, 1, 150, 200)
    assert full.sigma.shape == (1, 1, 150, 200) and full.rho.shape == (1, 3, 150, 200)
    # the layers are decompose's: R . S == I and R an albedo in [0, 1]
    torch.testing.assert_close(full.reflectance * full.shading, full.image, atol=1e-5, rtol=1e-4)
    assert float(full.reflectance.max()) <= 1
    # a 200 px photo is its own working resolution, and the preview reconstructs it too
    assert preview.size == (150, 200)
    torch.testing.assert_close(
        preview.reflectance * preview.shading, preview.image, atol=1e-5, rtol=1e-4
    )
    assert len(s.gallery) == 4 * 2  # sigma, rho, R, S of each alternation
    assert all(img.shape == (150, 200, 3) and img.dtype.name == "uint8" for img, _ in s.gallery)
    assert s.gallery[-1][1] == "2: Stage 2 shading S"
    info = s.info
    assert info["size"] == [200, 150] and info["working_size"] == [200, 150]
    assert len(info["solves"]) == 4 and info["seconds"] > 0
    assert s.objects is not None and s.objects.size == (150, 200)
    # the decomposition's own copies are dropped: the session holds the layers once
    assert s.result.reflectance is None and s.result.features is None


def test_progress_goes_through_stage_0_and_every_alternation(photos):
    seen: list[tuple[float, str]] = []
    open_photo(
        photos["small"],
        Parameters().replace(iterations=2),
        progress=lambda f, m: seen.append((f, m)),
    )
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[0] == 0 and fractions[-1] == 3 / 4
    messages = [m for _, m in seen]
    for expected in ("Stage 0: semantic features", "alternation 1 of 2", "alternation 2 of 2"):
        assert expected in messages
    assert messages[-1] == "full-resolution layers"


def test_the_kernels_compiling_shows_in_the_progress(photos, monkeypatch):
    import torchiid.app.session as session
    from torchiid.core.first_compile import COMPILING
    from torchiid.priors.kernel_runtime import compiled

    if compiled() is None:
        pytest.skip("the compiled kernels are off (no numba or TORCHIID_KERNELS=torch)")
    from numba import njit

    real = session.decompose

    def compiling(*args, **kwargs):  # as on a first run: a kernel of torchiid's compiles
        namespace = {"__name__": "torchiid.app_probe"}
        exec("def one(x):\n    return x + 1\n", namespace)
        njit(namespace["one"])(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(session, "decompose", compiling)
    seen: list[tuple[float, str]] = []
    open_photo(photos["small"], ONE, progress=lambda f, m: seen.append((f, m)))
    assert (0.0, COMPILING) in seen
    assert seen.index((0.0, COMPILING)) == seen.index((0.0, "Stage 0: semantic features")) + 1
    monkeypatch.setattr(session, "decompose", real)
    seen.clear()
    open_photo(photos["small"], ONE, progress=lambda f, m: seen.append((f, m)))
    assert COMPILING not in [m for _, m in seen]


def test_a_large_photo_goes_through_the_working_resolution(photos):
    s = open_photo(photos["large"], ONE.replace(max_side=128))
    assert s.full.image.shape == (1, 3, 1000, 1500)
    assert s.full.reflectance.shape == (1, 3, 1000, 1500)
    assert s.preview.size == (85, 128) == tuple(s.result.working_size)
    assert s.info["working_size"] == [128, 85] and s.objects.size == (85, 128)


def test_the_exif_orientation_is_applied(photos, tmp_path):
    exif = Image.Exif()
    exif[0x0112] = 6  # the camera was turned: the viewer rotates by 90 degrees
    path = tmp_path / "turned.jpg"
    with Image.open(photos["small"]) as rgb:  # 96 x 64
        rgb.convert("RGB").save(path, quality=95, exif=exif)
    s = open_photo(path, ONE)
    assert s.full.image.shape == (1, 3, 96, 64)  # upright: 64 wide, 96 high
    assert s.orientation == 6 and s.info["exif_orientation"] == 6


def test_bad_files_and_photos_over_the_memory_limit_are_refused_before_any_work(photos):
    with pytest.raises(ImageError, match="is not an image"):
        open_photo(photos["text"], ONE)
    with pytest.raises(ImageError, match="truncated or corrupt"):
        open_photo(photos["truncated"], ONE)
    with pytest.raises(ImageError, match="is 1x1 px; at least 60 px per side is needed"):
        open_photo(photos["tiny"], ONE)
    seen = []
    with pytest.raises(
        MemoryLimitError,
        match=r"^coffee.png: decomposing 96x64 px .* over the memory limit of 0.10 GB",
    ):
        open_photo(
            photos["small"], ONE, memory_limit=100_000_000, progress=lambda f, m: seen.append(m)
        )
    assert "Stage 0: semantic features" not in seen
