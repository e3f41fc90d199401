"""The ``/material`` group of an asset: the material as TOML text, its SI parameters and effects.

Written by :func:`write_material` (from a ``Material`` or its TOML text) and read
back by :func:`material_from_toml` and :func:`read_effects`
(docs/reference/asset-format.md). The writer and the reader of whole assets
(:mod:`~esmm.pipeline.asset.write`, :mod:`~esmm.pipeline.asset.read`) and the
tables rewriter (:mod:`~esmm.pipeline.asset.rewrite`) all go through here.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..errors import AssetError, EsmmError, InputError
from ..materials.effects import MaterialEffects
from ..materials.material import load_material
from ..network.tables import material_toml_text
from . import hdf5
from .schema import GROUPS


def material_text(material) -> tuple[str, dict[str, str]]:
    """TOML text and a few descriptive attributes of a material (object or TOML string)."""
    if material is None:
        return "", {}
    if isinstance(material, str):
        return material, {}
    attrs = {}
    for key in ("name", "model"):
        v = getattr(material, key, None)
        if v is not None:
            attrs[key] = v if isinstance(v, str) else getattr(v, "name", str(v))
    return material_toml_text(material), attrs


def material_from_toml(text: str):
    """The ``Material`` a stored TOML text describes (None for an empty text).

    Raises
    ------
    ConfigError
        The text is not a valid material (one line naming the key).
    """
    if not text:
        return None
    with tempfile.TemporaryDirectory(prefix="esmm-material-") as tmp:
        path = Path(tmp) / "material.toml"
        path.write_text(text, encoding="utf-8")
        return load_material(path)


def material_effects(material) -> MaterialEffects | None:
    """The material effects of a ``Material`` (``metadata["effects"]``, the ``[material.effects]``
    table of a discovery's params.toml) as a ``MaterialEffects``, or None when it has none.

    Raises
    ------
    ConfigError
        The table is malformed (one line naming the effect and key).
    """
    table = (getattr(material, "metadata", None) or {}).get("effects") if material is not None else None
    if not table:
        return None
    fx = MaterialEffects.from_toml_table(table, stress_unit=getattr(material, "stress_unit", None),
                                         where=f"{getattr(material, 'name', '') or 'material'}: [material.effects]")
    return fx if fx else None


def storable_effects(fx: MaterialEffects | None) -> tuple[MaterialEffects | None, list[str]]:
    """The part of *fx* an asset stores (``/material/effects``: QLV viscoelasticity, Mullins, damage,
    which ``esmm simulate`` applies), and one note per part it cannot store (cyclic softening,
    permanent set, stretch-dependent relaxation), for the caller to say: nothing is dropped silently."""
    if fx is None:
        return None, []
    dropped = [f"{n} (the asset format and the simulator have no {n.replace('_', ' ')})"
               for n in ("cyclic_softening", "permanent_set") if getattr(fx, n) is not None]
    v = fx.viscoelastic
    if v is not None and v.kappa:
        dropped.append(f"the stretch dependence of the relaxation (viscoelastic kappa = {v.kappa:g}): stored "
                       f"as QLV (kappa = 0), which relaxes as much at every stretch")
        v = replace(v, kappa=0.0)
    if v is not None and v.kappa_tau:
        dropped.append(f"the stretch dependence of the relaxation times (viscoelastic kappa_tau = {v.kappa_tau:g}): "
                       f"stored as QLV (kappa_tau = 0), which relaxes as fast at every stretch")
        v = replace(v, kappa_tau=0.0)
    kept = replace(fx, viscoelastic=v, cyclic_softening=None, permanent_set=None)
    return (kept if kept else None), dropped


def _param_units(material) -> dict[str, str]:
    """Parameter name -> SI unit ("Pa" for stress-like parameters, "1" otherwise)."""
    try:
        specs = material.model_obj.parameters
    except (AttributeError, Exception):  # noqa: BLE001 - a duck-typed material without specs
        return {}
    return {p.name: ("Pa" if getattr(p, "kind", "") == "stress" else "1") for p in specs}


def write_material(f: h5py.Group, material) -> None:
    """Write ``/material`` (TOML text, SI parameters, effects) into the open asset *f*.

    Raises
    ------
    InputError
        The material cannot be serialised as TOML.
    ConfigError
        A TOML text that is not a valid material.
    """
    if isinstance(material, str):
        parsed = material_from_toml(material)  # validates the text (ConfigError naming the key)
        if parsed is not None:
            attrs = {"name": parsed.name, "model": parsed.model}
            text, material = material, parsed
        else:
            text, attrs = material, {}
    else:
        text, attrs = material_text(material)
    if not text:
        raise InputError("material: cannot serialise it as TOML; pass a Material (or its TOML text)")
    g = hdf5.typed_group(f, "material", *GROUPS["/material"][:2])
    for k, v in attrs.items():
        g.attrs[k] = str(v)
    hdf5.put_text(g, "toml", text, description="the Material as TOML text (esmm material format)")
    _write_effects(g, material)
    params = getattr(material, "params", None)
    if not isinstance(params, dict) or not params:
        return
    units = _param_units(material)
    sets = [("parameters", params)]
    for d, over in sorted((getattr(material, "directions", None) or {}).items()):
        if over:
            sets.append((f"directions/{d}", over))
    for sub, values in sets:
        pg = g.require_group(sub)
        for grp in (pg, pg.parent):
            if grp.name != g.name and "esmm_type" not in grp.attrs:
                grp.attrs["esmm_type"] = "material_parameters"
                grp.attrs["esmm_version"] = 1
        for name, value in values.items():
            try:
                val = float(value)
            except (TypeError, ValueError):
                continue
            hdf5.put(pg, name, val, units.get(name, "1"), dtype=np.float64,
                     description="SI value (stress-like parameters in Pa)")


def _write_effects(g: h5py.Group, material) -> None:
    """``/material/effects``: the kept material effects in SI that an asset stores (docs/reference/asset-format.md;
    :func:`storable_effects`)."""
    fx, _ = storable_effects(material_effects(material))
    if fx is None:
        return
    d = fx.to_dict()
    eg = hdf5.typed_group(g, "effects", *GROUPS["/material/effects"][:2])
    eg.attrs["schema"] = d["schema"]
    eg.attrs["composition"] = d["composition"]
    eg.attrs["names"] = json.dumps(fx.names)
    eg.attrs["intervals"] = json.dumps(d.get("intervals", {}), sort_keys=True)
    if fx.viscoelastic is not None:
        v = fx.viscoelastic
        sg = hdf5.typed_group(eg, "viscoelastic", *GROUPS["/material/effects/viscoelastic"][:2])
        sg.attrs["model"] = "QLV: F = g_inf P + sum_i g_i h_i, G(t) = g_inf + sum_i g_i exp(-t/tau_i)"
        sg.attrs["reference"] = "instantaneous"
        sg.attrs["g_inf"] = float(v.g_inf)
        hdf5.put(sg, "g", np.asarray(v.g, float), "1", dtype=np.float64,
                 description="Prony weights, sorted by tau; g_inf = 1 - sum(g)")
        hdf5.put(sg, "tau", np.asarray(v.tau, float), "s", dtype=np.float64, description="relaxation times")
    if fx.mullins is not None:
        m = fx.mullins
        sg = hdf5.typed_group(eg, "mullins", *GROUPS["/material/effects/mullins"][:2])
        sg.attrs["model"] = "Ogden-Roxburgh: eta = 1 - (1/r) erf((W_max - W) / (m + beta W_max))"
        hdf5.put(sg, "r", float(m.r), "1", dtype=np.float64, description="largest softening is 1/r")
        hdf5.put(sg, "m", float(m.m), "Pa", dtype=np.float64, description="energy scale of the softening")
        hdf5.put(sg, "beta", float(m.beta), "1", dtype=np.float64, description="growth of the scale with W_max")
    if fx.damage is not None:
        da = fx.damage
        sg = hdf5.typed_group(eg, "damage", *GROUPS["/material/effects/damage"][:2])
        sg.attrs["model"] = ("Weibull with a floor: 1 - D = floor + (1 - floor) exp(-(((xi_max - onset)_+) / scale)^shape)"
                             if da.floor else "Weibull: 1 - D = exp(-(((xi_max - onset)_+) / scale)^shape)")
        hdf5.put(sg, "onset", float(da.onset), "1", dtype=np.float64,
                 description="uniaxial-equivalent stretch where damage starts")
        hdf5.put(sg, "scale", float(da.scale), "1", dtype=np.float64, description="stretch scale")
        hdf5.put(sg, "shape", float(da.shape), "1", dtype=np.float64, description="Weibull shape")
        if da.floor:
            hdf5.put(sg, "floor", float(da.floor), "1", dtype=np.float64,
                     description="fraction of the stress damage leaves at large stretch")


def read_effects(f: h5py.File) -> MaterialEffects | None:
    """``MaterialEffects`` from ``/material/effects`` (None when the group is absent).

    Raises
    ------
    AssetError
        The stored effects are not valid.
    """
    if "/material/effects" not in f:
        return None
    g = f["/material/effects"]
    d: dict[str, Any] = {}
    if "viscoelastic" in g:
        d["viscoelastic"] = {"g": np.atleast_1d(g["viscoelastic/g"][()]).astype(float).tolist(),
                             "tau": np.atleast_1d(g["viscoelastic/tau"][()]).astype(float).tolist()}
    if "mullins" in g:
        d["mullins"] = {k: float(g[f"mullins/{k}"][()]) for k in ("r", "m", "beta")}
    if "damage" in g:
        keys = ("onset", "scale", "shape") + (("floor",) if "damage/floor" in g else ())  # written where non-zero
        d["damage"] = {k: float(g[f"damage/{k}"][()]) for k in keys}
    try:
        d["intervals"] = json.loads(hdf5.attr_str(g.attrs.get("intervals", "{}")) or "{}")
    except json.JSONDecodeError:
        d["intervals"] = {}
    try:
        return MaterialEffects.from_dict(d, where="/material/effects")
    except EsmmError as exc:
        raise AssetError(str(exc)) from None
