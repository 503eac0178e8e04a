"""Evaluation: metrics, dataset readers, eval runs and cross-validation.

Metrics: WHDR, LMSE, SAW AP, si-MSE / DSSIM and the texture left in a shading
(:mod:`torchiid.eval.texture`); cross-validation of parameter choices in
:mod:`torchiid.eval.crossval`.
"""

from torchiid.eval.datasets import (
    DATASETS,
    DatasetError,
    DenseFolderDataset,
    DenseSample,
    IIWDataset,
    IIWSample,
    MITDataset,
    SAWDataset,
    SAWSample,
    open_dataset,
    read_id_list,
    saw_labels_from_release,
)
from torchiid.eval.dense import dssim, scale_to_match, si_mse, ssim
from torchiid.eval.lmse import local_mse, mit_lmse
from torchiid.eval.methods import METHODS, method_parameters, run_method
from torchiid.eval.options import EvalOptions
from torchiid.eval.outputs import EvalResult
from torchiid.eval.results import load_layer
from torchiid.eval.runner import EvalRunner, run_evaluation
from torchiid.eval.saw import average_precision, saw_ap, saw_scores
from torchiid.eval.scoring import COUNT_COLUMNS, METRICS, pooled_saw_ap, score_sample
from torchiid.eval.texture import local_linear_residual, texture_in_shading
from torchiid.eval.whdr import load_judgements, whdr

__all__ = [
    "COUNT_COLUMNS",
    "DATASETS",
    "DatasetError",
    "DenseFolderDataset",
    "DenseSample",
    "EvalOptions",
    "EvalResult",
    "EvalRunner",
    "IIWDataset",
    "IIWSample",
    "METHODS",
    "METRICS",
    "MITDataset",
    "SAWDataset",
    "SAWSample",
    "average_precision",
    "dssim",
    "load_judgements",
    "load_layer",
    "local_linear_residual",
    "local_mse",
    "method_parameters",
    "mit_lmse",
    "open_dataset",
    "pooled_saw_ap",
    "read_id_list",
    "run_evaluation",
    "run_method",
    "saw_ap",
    "saw_labels_from_release",
    "saw_scores",
    "scale_to_match",
    "score_sample",
    "si_mse",
    "ssim",
    "texture_in_shading",
    "whdr",
]
