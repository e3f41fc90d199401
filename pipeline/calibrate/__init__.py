"""Calibration: fit a material model to tensile tests (single fit and batch)."""

from .fit import FitResult, ParameterEstimate, fit_material, predict

__all__ = ["FitResult", "ParameterEstimate", "fit_material", "predict"]
