"""esmm: tensile data and a segmented organ in, real-time simulation assets out.

The public Python API (:mod:`esmm.pipeline.api`)::

    import esmm

    fit = esmm.calibrate(["tension.csv", "shear.csv"], out="fit")        # esmm calibrate
    made = esmm.prepare("liver.stl", output="liver.h5", material=fit.params_toml)   # esmm prepare
    asset = esmm.load_asset("liver.h5")                                   # esmm info
    run = esmm.simulate("liver.h5", duration="1 s")                       # esmm simulate

The names are loaded on first use, so that ``import esmm.cli`` (the command line)
does not pay for the whole library. The packages ``esmm.cli``, ``esmm.pipeline`` and
``esmm.configs`` are the repository's ``cli/``, ``pipeline/`` and ``configs/``; this
file is ``api/__init__.py`` (pyproject.toml, ``[tool.setuptools.package-dir]``).
"""

#: The public names and the module that holds each.
_API = {"calibrate": "esmm.pipeline.api", "prepare": "esmm.pipeline.api", "load_asset": "esmm.pipeline.api",
        "simulate": "esmm.pipeline.api", "CalibrationResult": "esmm.pipeline.api", "__version__": "esmm.pipeline"}

__all__ = sorted(_API)


def __getattr__(name: str):
    if name not in _API:
        raise AttributeError(f"module 'esmm' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(_API[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
