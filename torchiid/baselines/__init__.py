"""Baseline intrinsic-image methods used for comparison (colour Retinex)."""

from torchiid.baselines.retinex import ColorRetinex, color_retinex

__all__ = ["ColorRetinex", "color_retinex"]
