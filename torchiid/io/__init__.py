"""Reading and writing images: one loader that knows bit depth and colour encoding."""

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
]
