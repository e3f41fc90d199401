"""Calibration: fit a material model to tensile tests (one joint fit; a batch is esmm.pipeline.batch.calibrate).

Modules
-------
``problem``    the least-squares problem: parameter layout, weights, residual (shared with discover)
``intervals``  confidence intervals and identifiability (shared with discover)
``fit``        :func:`fit_material`, :func:`predict`, :class:`FitResult`
``config``     the ``[calibrate]`` table of a config file: :func:`load_calibrate_config`
``report``     params.toml, fit.json, fit.png, report.md
"""

from .config import CalibrateConfig, load_calibrate_config
from .fit import FitResult, ParameterEstimate, fit_material, predict

__all__ = ["CalibrateConfig", "FitResult", "ParameterEstimate", "fit_material", "load_calibrate_config", "predict"]
