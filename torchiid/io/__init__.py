"""Reading and writing images, and writing a decomposition's files.

One loader knows bit depth, colour encoding and EXIF orientation (:mod:`torchiid.io.image`);
:mod:`torchiid.io.layers` writes what ``torchiid decompose`` leaves in its output folder.
"""

from torchiid.io.image import (
    LoadedImage,
    linear_to_srgb,
    load_image,
    load_mask,
    read_exr,
    save_codes,
    save_image,
    save_uint8,
    srgb_to_linear,
)
from torchiid.io.inputs import IMAGE_SUFFIXES, collect_inputs
from torchiid.io.layers import layer_file_names, write_layers

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
    "layer_file_names",
    "write_layers",
    "IMAGE_SUFFIXES",
    "collect_inputs",
]
