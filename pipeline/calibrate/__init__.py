"""Calibration: fit a material model to tensile tests (one joint fit; a batch is esmm.pipeline.batch.calibrate).

Modules
-------
``problem``      the least-squares problem: parameter layout, weights, residual (shared with discover)
``intervals``    confidence intervals and identifiability (shared with discover)
``fit``          :func:`fit_material`, :func:`predict`, :class:`FitResult`
``failure``      failure tests: rupture, the intact part, ultimate stress, stretch at failure, moduli, censoring
``verdict``      good, poor or unusable, with the reasons
``calibration``  :func:`calibrate`: failure analysis, the fit of the intact parts and its verdict (the CLI's call)
``config``       the ``[calibrate]`` table of a config file: :func:`load_calibrate_config`
``report``       params.toml, fit.json and the writing of every output; ``markdown`` report.md,
                 ``html`` report.html, ``plots`` fit.png and the report's figures, ``inputs`` how each file was read
"""

from .calibration import Calibration, calibrate
from .config import CalibrateConfig, load_calibrate_config
from .fit import FitResult, ParameterEstimate, fit_material, predict

__all__ = ["CalibrateConfig", "Calibration", "FitResult", "ParameterEstimate", "calibrate", "fit_material",
           "load_calibrate_config", "predict"]
