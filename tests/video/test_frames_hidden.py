"""A folder of frames or masks leaves its hidden files out."""

from __future__ import annotations

import pytest
import torch

from torchiid.core.exceptions import TorchiidError
from torchiid.io import save_image
from torchiid.video.frames import list_images


def test_hidden_files_are_not_frames(tmp_path):
    for name in ("f1.png", "f2.png", "._f1.png", ".f0.png"):
        save_image(tmp_path / name, torch.full((3, 64, 64), 0.5))
    assert [p.name for p in list_images(tmp_path)] == ["f1.png", "f2.png"]


def test_a_folder_of_hidden_files_only_holds_no_frames(tmp_path):
    save_image(tmp_path / "._f1.png", torch.full((3, 64, 64), 0.5))
    with pytest.raises(TorchiidError, match="holds no image files"):
        list_images(tmp_path)
