"""The public Python API: what ``import esmm`` gives a notebook or a script.

Four functions, one per thing a simulation engineer does, each keyword-only after
its input, documented, returning a result object and printing nothing (progress goes
to an optional ``reporter``, :mod:`esmm.pipeline.progress`)::

    import esmm

    fit = esmm.calibrate(["tension.csv", "shear.csv"], out="fit")     # -> CalibrationResult
    made = esmm.prepare("liver.stl", output="liver.h5", material=fit.params_toml)   # -> PrepareResult
    asset = esmm.load_asset("liver.h5")                                # -> Asset (asset.accuracy)
    run = esmm.simulate("liver.h5", duration="1 s")                    # -> SimulationResult

They are the functions the command line runs (``esmm calibrate``, ``esmm prepare``,
``esmm info``, ``esmm simulate``), so a script and a shell give the same results.
Errors are :mod:`esmm.pipeline.errors` exceptions with a one-line message.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .asset import Asset, read_asset
from .calibrate.calibration import Calibration
from .calibrate.calibration import calibrate as calibrate_tests
from .calibrate.config import load_calibrate_config
from .calibrate.fit import FitResult
from .calibrate.report import write_outputs
from .calibrate.verdict import Verdict
from .materials.material import Material
from .prepare import PrepareResult
from .prepare import prepare as _prepare_stage
from .simulate.run import SimulationResult
from .simulate.run import simulate as _simulate_stage
from .tensile.data import TensileTest
from .tensile.files import read_tests

__all__ = ["CalibrationResult", "calibrate", "load_asset", "prepare", "simulate"]


@dataclass(frozen=True)
class CalibrationResult:
    """What :func:`calibrate` found.

    Attributes
    ----------
    material : Material
        The fitted material (SI parameters).
    calibration : Calibration
        The fit of the intact parts, each record's failure analysis and the verdict
        (:class:`esmm.pipeline.calibrate.calibration.Calibration`).
    outputs : dict of str to Path
        The files written into ``out`` (``params``, ``plot``, ``report``, ``html``,
        ``json``); empty when no folder was given.
    """

    material: Material
    calibration: Calibration
    outputs: dict[str, Path] = field(default_factory=dict)

    @property
    def fit(self) -> FitResult:
        """Parameters with their 95 % intervals, errors per file, warnings."""
        return self.calibration.result

    @property
    def tests(self) -> list[TensileTest]:
        """The records as read."""
        return list(self.calibration.tests)

    @property
    def verdict(self) -> Verdict:
        """Good, poor or unusable, with the reasons (``verdict.level``, ``verdict.short()``)."""
        return self.calibration.verdict

    @property
    def params_toml(self) -> Path | None:
        """The material file written (``out/params.toml``), for :func:`prepare`'s ``material``; None without ``out``."""
        return self.outputs.get("params")

    @property
    def rmse_pa(self) -> float:
        """Root-mean-square error of the fit [Pa]."""
        return float(self.fit.rmse)

    @property
    def nrmse(self) -> float:
        """The RMSE over the data's stress scale (a fraction)."""
        return float(self.fit.nrmse)

    @property
    def r2(self) -> float:
        """Coefficient of determination of the fit (1 is a perfect fit)."""
        return float(self.fit.r2)

    def summary(self) -> str:
        """One line: the model, the files, the errors with their units, and the verdict."""
        return (f"{self.fit.model} fitted to {len(self.tests)} file(s): RMSE {self.rmse_pa:.4g} Pa, "
                f"NRMSE {100 * self.nrmse:.3g} %, R² {self.r2:.3f}; verdict {self.verdict.level}")


def calibrate(files: str | os.PathLike | Sequence[str | os.PathLike], *, out: str | os.PathLike | None = None,
              model: str | None = None, config: str | os.PathLike | None = None, loss: str | None = None,
              n_starts: int | None = None, seed: int | None = None, weights: Mapping[str, Any] | None = None,
              fixed: Mapping[str, Any] | None = None, free: Sequence[str] | None = None,
              metadata: Mapping[str, Any] | None = None, reporter=None) -> CalibrationResult:
    """Fit one material to tensile-test files jointly, as ``esmm calibrate`` does: a record that
    failed is fitted up to its ultimate stress, and the fit gets a verdict.

    Parameters
    ----------
    files : path or sequence of paths
        Tensile records (CSV-like text; docs/reference/tensile-input.md), any mix of
        loading modes.
    out : path, optional
        Write ``params.toml``, ``fit.png``, ``report.md``, ``report.html`` and
        ``fit.json`` there (an empty or new folder).
    model : str, optional
        ``"esedf"`` (default) or ``"arruda-boyce"``.
    config : path, optional
        A calibrate config (a ``[calibrate]`` table); the keywords below override it.
    loss, n_starts, seed, weights, fixed, free
        As ``esmm calibrate``'s ``--loss``, ``--starts``, ``--seed``, ``--weight``,
        ``--fix`` (values with their unit, ``{"mu": "3e-6 MPa"}``) and ``--free``.
    metadata : mapping, optional
        What the files' sidecars would say (``gauge_length``, ``area``, ...), for
        every file.
    reporter : Reporter, optional
        Progress and warnings (:mod:`esmm.pipeline.progress`); silent by default.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    esmm.pipeline.errors.EsmmError
        An unreadable file, a bad option, or a fit that cannot run (one line saying what).
    """
    paths = [files] if isinstance(files, (str, os.PathLike)) else list(files)
    options = load_calibrate_config(config, model=model, loss=loss, n_starts=n_starts, seed=seed,
                                    weights=weights, fixed=fixed, free=free)
    tests = read_tests(paths, overrides=dict(metadata) if metadata else None, reporter=reporter)
    cal = calibrate_tests(tests, **options.fit_kwargs(), reporter=reporter)
    outputs = write_outputs(out, cal.result, tests, calibration=cal) if out is not None else {}
    name = f"fit of {', '.join(sorted({t.specimen for t in tests}))}"
    material = cal.result.material(name=name, source="esmm.calibrate " + " ".join(t.source.name for t in tests))
    return CalibrationResult(material=material, calibration=cal, outputs=dict(outputs))


def prepare(organ: str | os.PathLike, *, output: str | os.PathLike | None = None, **options) -> PrepareResult:
    """Turn an organ surface into a simulation asset (``esmm prepare``).

    Parameters
    ----------
    organ : path
        The organ's surface (STL, OBJ, PLY, VTK, gmsh) or a NIfTI label mask.
    output : path, optional
        The asset ``.h5`` (default ``<organ stem>.h5`` in the current folder); its
        XDMF sidecars go beside it.
    **options
        The keyword options of :func:`esmm.pipeline.prepare.prepare`: ``config``
        (``"coarse"``, ``"paper"``, ``"fine"`` or a TOML file), ``material`` (a preset
        name or a ``params.toml``, e.g. :attr:`CalibrationResult.params_toml`), ``unit``,
        ``size`` [m], ``nodes``, ``elements``, ``split``, ``compensate``, ``volume``,
        ``force``, ``reporter``, ...

    Returns
    -------
    PrepareResult
        The asset's path, network, tables, quality and cleaning reports, timings, warnings.
    """
    if isinstance(options.get("material"), os.PathLike):
        options["material"] = str(options["material"])
    return _prepare_stage(organ, output=output, **options)


def load_asset(path: str | os.PathLike) -> Asset:
    """Read and verify an asset (``esmm info``): its network, tables, material, reports and
    ``accuracy`` (how far to trust it: ``asset.accuracy.lines()``).

    Raises
    ------
    esmm.pipeline.errors.AssetError
        Missing, damaged, modified after it was written, or of a newer esmm.
    """
    return read_asset(path)


def simulate(asset: str | os.PathLike, **options) -> SimulationResult:
    """Run an asset in a scripted scene (``esmm simulate``).

    Parameters
    ----------
    asset : path
        An asset written by :func:`prepare`.
    **options
        The keyword options of :func:`esmm.pipeline.simulate.run.simulate`: ``scene``
        (``"default"``, ``"interactive"`` or a TOML file), ``duration`` (seconds or
        ``"500 ms"``), ``out_dir`` (default ``<asset stem>-sim`` beside it), ``video``,
        ``threads``, ``law``, ``effects``, ``method``, ``reporter``.

    Returns
    -------
    SimulationResult
        The files written and the run's :class:`~esmm.pipeline.simulate.summary.SimulationSummary`
        (``summary.real_time`` says the speed in words, ``summary.grasper`` the force).
    """
    return _simulate_stage(asset, **options)
