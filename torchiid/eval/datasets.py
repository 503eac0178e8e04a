"""Lazy readers for the evaluation datasets: IIW, MIT-Berkeley, SAW and dense-GT folders.

Every reader is a sequence of typed, frozen samples; files are read when a sample is
accessed, through the project's one loader (:func:`torchiid.io.load_image`, which keeps
16-bit depth). Images come out as ``(3, H, W)`` float32 **linear** RGB tensors: 16-bit PNGs
are divided by 65535 and taken as linear, 8-bit photos are divided by 255 and decoded from
sRGB. Layouts:

- **IIW** (Bell et al. 2014): ``<root>/data/<id>.png`` + ``<root>/data/<id>.json`` or the same
  files directly in ``<root>``; optional id list (one id per line, e.g.
  ``iiw_test_ids_narihira2015.txt``). Photos are 8-bit sRGB.
- **MIT-Berkeley** (Grosse et al. 2009; Barron & Malik's release): ``<root>/<object>/``
  with ``original.png``, ``diffuse.png``, ``reflectance.png``, ``shading.png``, ``mask.png``,
  all 16-bit linear PNGs (shading single-channel). The standard protocol's input is
  ``diffuse.png`` (the image without the specular layer) under ``mask.png``.
- **SAW** (Kovacs et al. 2017): ``<root>/<image_dir>/<id>.png`` (8-bit sRGB photos, the
  IIW/OpenSurfaces photos) and ``<root>/<label_dir>/<id>.npy`` (integer label map at the
  photo's resolution). The release's maps use 0 normal/depth discontinuity, 1 shadow
  boundary, 2 smooth, 100 unlabeled; they are converted to the convention of
  :mod:`torchiid.eval.saw` (0 unlabeled, 1 smooth, 2 shadow, 3 normal). Pass
  ``image_dir``/``label_dir`` for the release's folder names.
- **Dense folder** (ARAP, Sintel and similar): ``<root>/<name>.png`` input,
  ``<name>-reflectance.png``, ``<name>-shading.png`` and optionally ``<name>-mask.png``.
  16-bit files are linear; 8-bit files are sRGB-decoded unless ``srgb=False``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
import torch

from torchiid.core.exceptions import ImageError, ParameterError, TorchiidError
from torchiid.io import load_image, load_mask, srgb_to_linear

__all__ = [
    "DATASETS",
    "DatasetError",
    "IIWSample",
    "DenseSample",
    "SAWSample",
    "IIWDataset",
    "MITDataset",
    "SAWDataset",
    "DenseFolderDataset",
    "open_dataset",
    "read_id_list",
    "saw_labels_from_release",
]

DATASETS = ("iiw", "mit", "saw", "dense")
"""The benchmark layouts (see :mod:`torchiid.eval.datasets`)."""

MIT_FILES = ("original.png", "diffuse.png", "reflectance.png", "shading.png", "mask.png")


class DatasetError(TorchiidError):
    """A dataset directory or file is missing, incomplete or unreadable."""


def _read(path: Path, srgb: bool | None = None) -> torch.Tensor:
    """Read an image through :func:`torchiid.io.load_image` as ``(3, H, W)`` float32 linear.

    ``srgb``: decode sRGB; ``None`` decodes 8-bit files and keeps 16-bit files as stored.
    Alpha channels are rejected. Errors become :class:`DatasetError`.
    """
    if not path.is_file():
        raise DatasetError(f"missing file {path}")
    try:
        loaded = load_image(path, linear=True, alpha="error", min_side=1)
    except ImageError as exc:
        raise DatasetError(str(exc)) from exc
    decode = srgb if srgb is not None else loaded.bit_depth == 8
    return srgb_to_linear(loaded.image) if decode else loaded.image


def _read_file(path: Path, what: str, read: Callable[[Path], Any]) -> Any:
    """``read(path)``; a file that cannot be read or parsed is a :class:`DatasetError`."""
    try:
        return read(path)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"cannot read {what} {path}: {exc}") from exc


def _read_mask(path: Path) -> torch.Tensor:
    try:
        return load_mask(path)
    except ImageError as exc:
        raise DatasetError(str(exc)) from exc


def _gray_if_equal(x: torch.Tensor) -> torch.Tensor:
    """``(3, H, W)`` -> ``(1, H, W)`` when the channels are equal (a gray file)."""
    return x[:1] if torch.equal(x[0], x[1]) and torch.equal(x[0], x[2]) else x


def read_id_list(path: str | Path) -> list[str]:
    """Read a split file with one id per line (blank lines and ``#`` comments skipped)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"missing id list {path}")
    lines = (ln.split("#", 1)[0].strip() for ln in path.read_text().splitlines())
    return [ln for ln in lines if ln]


def saw_labels_from_release(labels: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Map SAW release labels (0 ND, 1 SB, 2 smooth, other = ignored) to 3/2/1/0."""
    lab = torch.as_tensor(np.asarray(labels)).long()
    out = torch.zeros_like(lab)
    out[lab == 2] = 1
    out[lab == 1] = 2
    out[lab == 0] = 3
    return out


@dataclass(frozen=True)
class IIWSample:
    """One IIW photo. ``image``: ``(3, H, W)`` float32 linear; ``mask``: ``(1, H, W)`` bool."""

    id: str
    image: torch.Tensor
    judgements: dict[str, Any]
    mask: torch.Tensor


@dataclass(frozen=True)
class DenseSample:
    """An image with dense ground truth (MIT-Berkeley, ARAP, Sintel).

    Attributes:
        id: object or file name.
        image: ``(3, H, W)`` float32 linear input.
        reflectance: ``(3, H, W)`` float32 linear ground-truth reflectance.
        shading: ``(1, H, W)`` (or ``(3, H, W)`` if stored in colour) linear shading.
        mask: ``(1, H, W)`` bool, pixels to evaluate.
    """

    id: str
    image: torch.Tensor
    reflectance: torch.Tensor
    shading: torch.Tensor
    mask: torch.Tensor


@dataclass(frozen=True)
class SAWSample:
    """One SAW photo: ``image`` ``(3, H, W)`` linear, ``labels`` ``(H, W)`` int64, ``mask``."""

    id: str
    image: torch.Tensor
    labels: torch.Tensor
    mask: torch.Tensor


S = TypeVar("S")


class _LazyDataset(Generic[S]):
    """A sequence of samples loaded on access by :meth:`load`."""

    ids: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, index: int) -> S:
        return self.load(self.ids[index])

    def __iter__(self) -> Iterator[S]:
        for i in self.ids:
            yield self.load(i)

    def load(self, sample_id: str) -> S:  # pragma: no cover - abstract
        """Load the sample with the given id."""
        raise NotImplementedError


def _same_size(where: Path, *tensors: torch.Tensor) -> None:
    sizes = sorted({tuple(t.shape[-2:]) for t in tensors})
    if len(sizes) != 1:
        raise DatasetError(f"{where}: files differ in size {sizes}")


def _require_dir(root: str | Path, what: str) -> Path:
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{what} directory {root} does not exist")
    return root


def _photos_with(image_dir: Path, companion: Callable[[str], Path]) -> list[str]:
    """Stems of the ``*.png`` photos whose companion file exists, in numeric id order."""
    stems = (p.stem for p in image_dir.glob("*.png") if companion(p.stem).is_file())
    return sorted(stems, key=lambda s: (len(s), s))


def _select(found: Sequence[str], ids: Sequence[str] | str | Path | None, what: str) -> tuple:
    if ids is None:
        if not found:
            raise DatasetError(f"no {what} found")
        return tuple(found)
    wanted = read_id_list(ids) if isinstance(ids, (str, Path)) else [str(i) for i in ids]
    missing = sorted(set(wanted) - set(found))
    if missing:
        more = f" (and {len(missing) - 5} more)" if len(missing) > 5 else ""
        raise DatasetError(f"{len(missing)} {what} missing: {missing[:5]}{more}")
    return tuple(wanted)


class IIWDataset(_LazyDataset[IIWSample]):
    """Intrinsic Images in the Wild photos with their judgement JSON (see module docstring).

    Args:
        root: the IIW directory (holding ``data/`` or the files themselves).
        ids: ``None`` for every ``<id>.png`` with a matching ``<id>.json``, a sequence of ids
            or the path of an id list file.
    """

    def __init__(self, root: str | Path, ids: Sequence[str] | str | Path | None = None) -> None:
        root = _require_dir(root, "IIW")
        self.dir = root / "data" if (root / "data").is_dir() else root
        found = _photos_with(self.dir, lambda stem: self.dir / f"{stem}.json")
        self.ids = _select(found, ids, f"IIW photos with judgements in {self.dir}")

    def load(self, sample_id: str) -> IIWSample:
        """Read photo ``<id>.png`` (sRGB → linear) and ``<id>.json``."""
        image = _read(self.dir / f"{sample_id}.png", srgb=True)
        jpath = self.dir / f"{sample_id}.json"
        judgements = _read_file(jpath, "judgements", lambda p: json.loads(p.read_text()))
        mask = torch.ones(1, *image.shape[-2:], dtype=torch.bool)
        return IIWSample(sample_id, image, judgements, mask)


class MITDataset(_LazyDataset[DenseSample]):
    """MIT-Berkeley intrinsic images (16-bit linear PNGs, see module docstring).

    Args:
        root: directory with one folder per object.
        objects: object names (default: every folder holding all five files).
        input: which file is the input image, ``"diffuse"`` (standard protocol) or
            ``"original"`` (with specularities).
    """

    def __init__(
        self, root: str | Path, objects: Sequence[str] | None = None, input: str = "diffuse"
    ) -> None:
        self.root = _require_dir(root, "MIT-Berkeley")
        if input not in ("diffuse", "original"):
            raise DatasetError(f"expected input 'diffuse' or 'original', got {input!r}")
        self.input = input
        complete = sorted(
            d.name for d in self.root.iterdir() if all((d / f).is_file() for f in MIT_FILES)
        )
        if objects is not None:
            for name in objects:
                absent = [f for f in MIT_FILES if not (self.root / name / f).is_file()]
                if absent:
                    raise DatasetError(f"MIT object {self.root / name} lacks {absent}")
        self.ids = _select(complete, objects, f"MIT objects in {self.root}")

    def load(self, sample_id: str) -> DenseSample:
        """Read one object's input, reflectance, shading and mask."""
        d = self.root / sample_id
        image = _read(d / f"{self.input}.png", srgb=False)
        refl = _read(d / "reflectance.png", srgb=False)
        shading = _read(d / "shading.png", srgb=False).mean(dim=0, keepdim=True)
        mask = _read_mask(d / "mask.png")
        _same_size(d, image, refl, shading, mask)
        return DenseSample(sample_id, image, refl, shading, mask)


class SAWDataset(_LazyDataset[SAWSample]):
    """Shading Annotations in the Wild photos and pixel labels (see module docstring).

    Args:
        root: SAW directory.
        ids: ``None`` (every photo with a label map), ids, or an id list file.
        image_dir: sub-folder of the photos (8-bit sRGB ``<id>.png``).
        label_dir: sub-folder of the label maps (``<id>.npy``).
        release_labels: the maps use the release's 0/1/2/100 codes (converted on load);
            ``False`` if they already use 0 unlabeled / 1 smooth / 2 shadow / 3 normal.
    """

    def __init__(
        self,
        root: str | Path,
        ids: Sequence[str] | str | Path | None = None,
        image_dir: str = "images",
        label_dir: str = "labels",
        release_labels: bool = True,
    ) -> None:
        root = _require_dir(root, "SAW")
        self.image_dir = _require_dir(root / image_dir, "SAW image")
        self.label_dir = _require_dir(root / label_dir, "SAW label")
        self.release_labels = release_labels
        found = _photos_with(self.image_dir, lambda stem: self.label_dir / f"{stem}.npy")
        self.ids = _select(found, ids, f"SAW photos with labels in {root}")

    def load(self, sample_id: str) -> SAWSample:
        """Read photo (sRGB → linear) and label map."""
        image = _read(self.image_dir / f"{sample_id}.png", srgb=True)
        lpath = self.label_dir / f"{sample_id}.npy"
        raw = _read_file(lpath, "SAW labels", lambda p: np.load(p, allow_pickle=False))
        if raw.shape != tuple(image.shape[-2:]):
            raise DatasetError(
                f"{lpath}: labels {raw.shape} do not match photo {tuple(image.shape[-2:])}"
            )
        labels = (
            saw_labels_from_release(raw) if self.release_labels else torch.as_tensor(raw).long()
        )
        return SAWSample(sample_id, image, labels, (labels > 0)[None])


class DenseFolderDataset(_LazyDataset[DenseSample]):
    """A flat folder of images with dense ground truth (see module docstring).

    Args:
        root: the folder.
        srgb: decode 8-bit files from sRGB (``None``: 8-bit sRGB, 16-bit linear).
    """

    SUFFIXES = ("-reflectance", "-shading", "-mask")

    def __init__(self, root: str | Path, srgb: bool | None = None) -> None:
        self.root = _require_dir(root, "dense ground-truth")
        self.srgb = srgb
        names = sorted(
            p.stem for p in self.root.glob("*.png") if not p.stem.endswith(self.SUFFIXES)
        )
        incomplete = [
            n
            for n in names
            if not all((self.root / f"{n}{s}.png").is_file() for s in self.SUFFIXES[:2])
        ]
        if incomplete:
            raise DatasetError(
                f"{self.root}: images without -reflectance.png / -shading.png: {incomplete[:5]}"
            )
        self.ids = _select(names, None, f"images in {self.root}")

    def load(self, sample_id: str) -> DenseSample:
        """Read the image, its reflectance, shading and optional mask."""
        image = _read(self.root / f"{sample_id}.png", self.srgb)
        refl = _read(self.root / f"{sample_id}-reflectance.png", self.srgb)
        shading = _gray_if_equal(_read(self.root / f"{sample_id}-shading.png", self.srgb))
        mpath = self.root / f"{sample_id}-mask.png"
        if mpath.is_file():
            mask = _read_mask(mpath)
        else:
            mask = torch.ones(1, *image.shape[-2:], dtype=torch.bool)
        _same_size(self.root / sample_id, image, refl, shading, mask)
        return DenseSample(sample_id, image, refl, shading, mask)


Sample = IIWSample | DenseSample | SAWSample
EvalDataset = IIWDataset | MITDataset | SAWDataset | DenseFolderDataset


def open_dataset(
    dataset: str,
    root: str | Path,
    ids: Sequence[str] | str | Path | None = None,
    *,
    input: str = "diffuse",
) -> EvalDataset:
    """Open an evaluation dataset by layout name.

    Args:
        dataset: ``"iiw"``, ``"mit"``, ``"saw"`` or ``"dense"`` (see the module notes).
        root: the dataset directory.
        ids: the ids to evaluate, in this order: a sequence, or the path of a file of ids
            (one a line, e.g. an IIW/SAW test split); ``None`` for every image.
        input: MIT input image, ``"diffuse"`` (the standard protocol) or ``"original"``.

    Returns:
        The dataset reader; its ``ids`` are the selected ids.

    Raises:
        DatasetError: missing directory or files, or ids that are not in the dataset.
        ParameterError: unknown ``dataset``.
    """
    check_dataset(dataset)
    root = Path(root)
    from_file = isinstance(ids, (str, Path))
    wanted = read_id_list(ids) if from_file else None if ids is None else [str(i) for i in ids]
    if dataset == "iiw":
        return IIWDataset(root, ids=wanted)
    if dataset == "mit":
        return MITDataset(root, objects=wanted, input=input)
    if dataset == "saw":
        return SAWDataset(root, ids=wanted)
    ds = DenseFolderDataset(root)
    if wanted is not None:
        missing = sorted(set(wanted) - set(ds.ids))
        if missing:
            which = f"ids of {ids}" if from_file else "of the given ids"
            raise DatasetError(f"{len(missing)} {which} are not in {root}: {missing[:5]}")
        ds.ids = tuple(wanted)
    return ds


def check_dataset(dataset: str) -> None:
    """Raise :class:`ParameterError` unless ``dataset`` is one of :data:`DATASETS`."""
    if dataset not in DATASETS:
        raise ParameterError(f"unknown dataset {dataset!r}; choose one of {', '.join(DATASETS)}")
