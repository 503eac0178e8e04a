"""Reading and writing images, and writing a decomposition's files.

One loader knows bit depth, colour encoding and EXIF orientation (:mod:`torchiid.io.image`,
built from :mod:`~torchiid.io.decode`, :mod:`~torchiid.io.damage`,
:mod:`~torchiid.io.orientation`, :mod:`~torchiid.io.bitdepth` and
:mod:`~torchiid.io.validate`); :mod:`torchiid.io.write` saves images atomically;
:mod:`torchiid.io.layers` writes what ``torchiid decompose`` leaves in its output folder, as
one :mod:`output set <torchiid.io.output_set>`. The names below load on first use
(:mod:`torchiid._lazy`), so :mod:`~torchiid.io.inputs` and :mod:`~torchiid.io.output_set`
import without torch.
"""

from typing import TYPE_CHECKING

from torchiid._lazy import lazy_names

if TYPE_CHECKING:  # what static tools see; at run time: __getattr__
    from torchiid.core.colour import linear_to_srgb, srgb_to_linear
    from torchiid.io.exr import read_exr
    from torchiid.io.image import LoadedImage, load_image, load_mask
    from torchiid.io.inputs import IMAGE_SUFFIXES, collect_inputs
    from torchiid.io.layers import ExtraOutputs, layer_file_names, write_layers
    from torchiid.io.write import save_codes, save_image, save_uint8

__all__ = [
    "LoadedImage",
    "linear_to_srgb",
    "load_image",
    "load_mask",
    "read_exr",
    "save_image",
    "save_uint8",
    "save_codes",
    "srgb_to_linear",
    "ExtraOutputs",
    "layer_file_names",
    "write_layers",
    "IMAGE_SUFFIXES",
    "collect_inputs",
]

_SOURCES = {
    **dict.fromkeys(["linear_to_srgb", "srgb_to_linear"], "torchiid.core.colour"),
    "read_exr": "torchiid.io.exr",
    **dict.fromkeys(["LoadedImage", "load_image", "load_mask"], "torchiid.io.image"),
    **dict.fromkeys(["IMAGE_SUFFIXES", "collect_inputs"], "torchiid.io.inputs"),
    **dict.fromkeys(["ExtraOutputs", "layer_file_names", "write_layers"], "torchiid.io.layers"),
    **dict.fromkeys(["save_codes", "save_image", "save_uint8"], "torchiid.io.write"),
}
__getattr__, __dir__ = lazy_names(__name__, _SOURCES, globals())
