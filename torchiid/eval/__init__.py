"""Evaluation: WHDR, LMSE, SAW AP, si-MSE / DSSIM metrics and dataset readers."""

from torchiid.eval.datasets import (
    DatasetError,
    DenseFolderDataset,
    DenseSample,
    IIWDataset,
    IIWSample,
    MITDataset,
    SAWDataset,
    SAWSample,
    read_id_list,
    saw_labels_from_release,
)
from torchiid.eval.dense import dssim, scale_to_match, si_mse, ssim
from torchiid.eval.lmse import local_mse, mit_lmse
from torchiid.eval.saw import average_precision, saw_ap, saw_scores
from torchiid.eval.whdr import load_judgements, whdr

__all__ = [
    "DatasetError",
    "DenseFolderDataset",
    "DenseSample",
    "IIWDataset",
    "IIWSample",
    "MITDataset",
    "SAWDataset",
    "SAWSample",
    "average_precision",
    "dssim",
    "load_judgements",
    "local_mse",
    "mit_lmse",
    "read_id_list",
    "saw_ap",
    "saw_labels_from_release",
    "saw_scores",
    "scale_to_match",
    "si_mse",
    "ssim",
    "whdr",
]
