"""Export files in the shapes testing-machine software writes (the contract of
shared/specs/tensile-data.md, which esmm's reader must read as written).

Formats (``FORMATS``):

* ``comments``     ``# key: value`` metadata, units in brackets (``time [s],displacement [mm],force [N]``),
                   comma or tab delimited;
* ``parentheses``  ``Time (s),Extension (mm),Load (N)`` and a TOML sidecar with the specimen keys;
* ``units_row``    bare names and a units row under them (``(s),(um),(mN)`` or ``s,mm,N``), a sidecar;
                   an absolute crosshead ``Position`` channel (no natural zero) in some files;
* ``european``     ``;`` delimited with a decimal comma, German or English names, ``#`` metadata written
                   with a decimal comma;
* ``bluehill``     an Instron Bluehill-like export: ``Specimen properties : Length,"18.50000",mm``
                   preamble, quoted values with five decimals, derived columns (``Tensile stress``,
                   ``Tenacity``, ``Tensile extension``, ``Tensile strain (Extension)``), sometimes
                   ``Results Table`` lines after the data;
* ``gbk``          Chinese headers (时间,位移,力) in the GBK encoding with a units row, stated by the
                   sidecar's ``encoding`` (like the VHB 4910 files of the shared data);
* ``processed``    stretch or strain and nominal stress (time optional), as a lab's own script writes.

Numbers carry as many decimals as the channel's resolution needs (Bluehill: always five).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

FORMATS = ("comments", "parentheses", "units_row", "european", "bluehill", "gbk", "processed")
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "min": 60.0}
DISP_UNITS = {"mm": 1e-3, "um": 1e-6, "m": 1.0}
FORCE_UNITS = {"N": 1.0, "mN": 1e-3, "kN": 1e3}
STRESS_UNITS = {"Pa": 1.0, "kPa": 1e3, "MPa": 1e6}


def decimals(step: float) -> int:
    """Decimals that resolve half of ``step`` (in the unit written)."""
    return int(np.clip(np.ceil(-np.log10(max(step, 1e-12) / 2.0)), 0, 10))


def column(v: np.ndarray, nd: int, comma: bool = False, quote: bool = False) -> list[str]:
    s = [f"{a:.{nd}f}" for a in np.asarray(v, dtype=float)]
    s = ["0." + "0" * nd if x in ("-0", "-0." + "0" * nd) else x for x in s]
    if comma:
        s = [x.replace(".", ",") for x in s]
    if quote:
        s = [f'"{x}"' for x in s]
    return s


def measured_length(v_m: float) -> float:
    """A length as the lab measures it [m]: to 0.01 mm from 1 mm up (calipers), to 1 um below
    (a micrometer or an optical measurement)."""
    mm = v_m * 1e3
    return round(mm, 2 if mm >= 1.0 else 3) * 1e-3


def measured_area(v_m2: float) -> float:
    """An area as written [m2]: four significant digits in mm2."""
    return float(f"{v_m2 * 1e6:.4g}") * 1e-6


def _length(v_m: float, comma: bool = False) -> str:
    """A measured length written in mm (never three decimals after a decimal comma, which the
    contract calls ambiguous: four instead)."""
    mm = v_m * 1e3
    nd = 2 if mm >= 1.0 else 4
    s = f"{mm:.{nd}f}"
    return (s.replace(".", ",") if comma else s) + " mm"


def _area(v_m2: float) -> str:
    return f"{v_m2 * 1e6:.4g} mm2"


def geometry_lines(rec: dict, comma: bool = False) -> list[tuple[str, str]]:
    """(key, value) of the stated specimen geometry."""
    g = rec["stated"]
    out = [("gauge_length", _length(rec["gauge_length"], comma))]
    if "area" in g:
        v = _area(g["area"])
        out.append(("area", v.replace(".", ",") if comma else v))
    if "diameter" in g:
        out.append(("diameter", _length(g["diameter"], comma)))
    if "width" in g:
        out += [("width", _length(g["width"], comma)), ("thickness", _length(g["thickness"], comma))]
    return out


def metadata_pairs(rec: dict, comma: bool = False) -> list[tuple[str, str]]:
    out = [("specimen", rec["specimen"])] + geometry_lines(rec, comma)
    if rec["mode"] != "uniaxial":
        out.append(("mode", rec["mode"]))
    return out + [("tissue", rec["tissue"]), ("notes", rec["notes"])]


def sidecar(path: Path, pairs: list[tuple[str, str]], extra: str = "") -> Path:
    """A TOML sidecar of string values (written by hand: no TOML library needed)."""
    lines = [f'{k} = "{v}"' for k, v in pairs] + ([extra] if extra else [])
    side = path.with_suffix(".toml")
    side.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return side


def _channels(rec: dict, units: tuple[str, str, str], *, absolute: float = 0.0):
    """Time, displacement and force in the units written, with their decimals."""
    tu, du, fu = units
    t = rec["time_s"] / TIME_UNITS[tu]
    d = (rec["disp_m"] + absolute) / DISP_UNITS[du]
    f = rec["force_N"] / FORCE_UNITS[fu]
    nd_t = decimals(rec["time_step_s"] / TIME_UNITS[tu])
    nd_d = decimals(rec["disp_step_m"] / DISP_UNITS[du])
    nd_f = decimals(rec["force_step_N"] / FORCE_UNITS[fu])
    return (t, nd_t), (d, nd_d), (f, nd_f)


def _units(rng: np.random.Generator, rec: dict) -> tuple[str, str, str]:
    tu = "s" if rng.uniform() < 0.8 else str(rng.choice(["ms", "min"]))
    du = "mm" if rng.uniform() < 0.75 else ("um" if rec["gauge_length"] < 0.03 else "m")
    peak = float(np.max(np.abs(rec["force_N"])))
    fu = "mN" if peak < 0.5 and rng.uniform() < 0.6 else ("kN" if peak > 2e3 and rng.uniform() < 0.6 else "N")
    return tu, du, fu


def _rows(cols: list[list[str]], delim: str) -> list[str]:
    return [delim.join(r) for r in zip(*cols)]


_NAMES = {
    "time": ["time", "Time", "Test time", "Elapsed time", "t"],
    "disp": ["displacement", "Extension", "Crosshead", "Elongation", "Crosshead displacement"],
    "force": ["force", "Load", "Standard force", "Axial force", "Force"],
}


def _name(rng: np.random.Generator, q: str) -> str:
    return str(rng.choice(_NAMES[q]))


def write_comments(path: Path, rec: dict, rng: np.random.Generator) -> dict:
    units = _units(rng, rec)
    (t, a), (d, b), (f, c) = _channels(rec, units)
    delim = "," if rng.uniform() < 0.8 else "\t"
    names = [_name(rng, "time"), _name(rng, "disp"), _name(rng, "force")]
    head = [f"# {k}: {v}" for k, v in metadata_pairs(rec)]
    head.append(delim.join(f"{n} [{u}]" for n, u in zip(names, units)))
    rows = _rows([column(t, a), column(d, b), column(f, c)], delim)
    path.write_text("\n".join(head + rows) + "\n", encoding="utf-8")
    return {"format": "comments", "units": list(units), "headers": names, "delimiter": delim}


def write_parentheses(path: Path, rec: dict, rng: np.random.Generator) -> dict:
    units = _units(rng, rec)
    (t, a), (d, b), (f, c) = _channels(rec, units)
    names = [_name(rng, "time"), _name(rng, "disp"), _name(rng, "force")]
    head = ",".join(f"{n} ({u})" for n, u in zip(names, units))
    rows = _rows([column(t, a), column(d, b), column(f, c)], ",")
    path.write_text("\n".join([head] + rows) + "\n", encoding="utf-8")
    sidecar(path, metadata_pairs(rec))
    return {"format": "parentheses", "units": list(units), "headers": names, "sidecar": path.with_suffix(".toml").name}


def write_units_row(path: Path, rec: dict, rng: np.random.Generator) -> dict:
    units = _units(rng, rec)
    absolute = float(rng.uniform(0.03, 0.3)) if rng.uniform() < 0.4 else 0.0
    (t, a), (d, b), (f, c) = _channels(rec, units, absolute=absolute)
    disp_name = str(rng.choice(["Position", "Crosshead position"])) if absolute else _name(rng, "disp")
    names = [_name(rng, "time"), disp_name, _name(rng, "force")]
    paren = rng.uniform() < 0.6
    urow = ",".join(f"({u})" if paren else u for u in units)
    rows = _rows([column(t, a), column(d, b), column(f, c)], ",")
    path.write_text("\n".join([",".join(names), urow] + rows) + "\n", encoding="utf-8")
    sidecar(path, metadata_pairs(rec))
    return {"format": "units_row", "units": list(units), "headers": names, "absolute_position_m": absolute,
            "sidecar": path.with_suffix(".toml").name}


def write_european(path: Path, rec: dict, rng: np.random.Generator) -> dict:
    units = ("s", "mm", "N") if rng.uniform() < 0.7 else _units(rng, rec)
    (t, a), (d, b), (f, c) = _channels(rec, units)
    german = rng.uniform() < 0.5
    names = ["Prüfzeit", "Standardweg", "Standardkraft"] if german else ["Time", "Extension", "Force"]
    head = [f"# {k}: {v}" for k, v in metadata_pairs(rec, comma=True)]
    head.append(";".join(f"{n} [{u}]" for n, u in zip(names, units)))
    rows = _rows([column(t, a, True), column(d, b, True), column(f, c, True)], ";")
    path.write_text("\n".join(head + rows) + "\n", encoding="utf-8")
    return {"format": "european", "units": list(units), "headers": names, "delimiter": ";", "decimal": ","}


def _bluehill_preamble(rec: dict, rng: np.random.Generator) -> list[str]:
    g = rec["stated"]
    out = [f'Specimen properties : Specimen label,"{rec["specimen"]}"',
           f'Specimen properties : Length,"{rec["gauge_length"] * 1e3:.5f}",mm']
    if "diameter" in g:
        out.append(f'Specimen properties : Diameter,"{g["diameter"] * 1e3:.5f}",mm')
    elif "width" in g:
        out += [f'Specimen properties : Width,"{g["width"] * 1e3:.5f}",mm',
                f'Specimen properties : Thickness,"{g["thickness"] * 1e3:.5f}",mm']
    else:
        out.append(f'Specimen properties : Area,"{g["area"] * 1e6:.5f}",mm^2')
    out.append(f'Test : Rate 1,"{rec["speed_mm_per_min"]:.5f}",mm/min')
    return out + [""]


def write_bluehill(path: Path, rec: dict, rng: np.random.Generator) -> dict:
    """Instron Bluehill-like export (uniaxial): raw Extension and Load with derived columns."""
    q = lambda v: column(v, 5, quote=True)  # noqa: E731 - Bluehill writes five decimals, quoted
    ext, load, t = rec["disp_m"] * 1e3, rec["force_N"], rec["time_s"]
    load5 = np.round(load, 5)
    stress = load5 / rec["area_stated_m2"] / 1e6
    tex = float(rng.uniform(5.0, 50.0))
    cols = [q(ext), q(load), q(stress), q(t), q(np.zeros_like(t)), q(load5 / tex), q(ext), q(ext / (rec["gauge_length"] * 1e3))]
    head = ["Extension,Load,Tensile stress,Time,PIP count,Tenacity,Tensile extension,Tensile strain (Extension)",
            "(mm),(N),(MPa),(s),,(N/tex),(mm),(mm/mm)"]
    lines = _bluehill_preamble(rec, rng) + head + _rows(cols, ",")
    trailer = rng.uniform() < 0.5
    if trailer:
        lines += ["", "Results Table 1", "", "", "Results Table 2", ""]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return {"format": "bluehill", "units": ["s", "mm", "N"], "results_table": bool(trailer)}


def write_gbk(path: Path, rec: dict, rng: np.random.Generator) -> dict:
    units = ("s", "mm", "N")
    (t, a), (d, b), (f, c) = _channels(rec, units)
    rows = _rows([column(t, a), column(d, b), column(f, c)], ",")
    text = "\n".join(["", "时间,位移,力", "(s),(mm),(N)"] + rows) + "\n"
    path.write_bytes(text.encode("gbk"))
    sidecar(path, metadata_pairs(rec), extra='encoding = "gbk"')
    return {"format": "gbk", "units": list(units), "encoding": "gbk", "sidecar": path.with_suffix(".toml").name}


def write_processed(path: Path, rec: dict, rng: np.random.Generator) -> dict:
    """Stretch (or strain, or shear strain) and nominal stress, as computed by the lab from the
    recorded channels and the stated geometry."""
    area = rec["area_stated_m2"]
    x = rec["disp_m"] / rec["gauge_length"] + (0.0 if rec["mode"] == "simple_shear" else 1.0)
    stress = rec["force_N"] / area
    su = "kPa" if np.max(np.abs(stress)) < 2e6 else "MPa"
    nd_x = decimals(rec["disp_step_m"] / rec["gauge_length"])
    nd_s = decimals(rec["force_step_N"] / area / STRESS_UNITS[su])
    head = [f"# specimen: {rec['specimen']}", f"# mode: {rec['mode']}", f"# tissue: {rec['tissue']}"]
    with_time = rng.uniform() < 0.6
    cols, names = [], []
    if with_time:
        cols.append(column(rec["time_s"], decimals(rec["time_step_s"])))
        names.append("time [s]")
    if rec["mode"] == "simple_shear":
        cols += [column(x, nd_x), column(stress / STRESS_UNITS[su], nd_s)]
        names += ["shear strain", f"shear stress [{su}]"]
    elif rng.uniform() < 0.5:
        cols += [column(x, nd_x), column(stress / STRESS_UNITS[su], nd_s)]
        names += ["stretch", f"nominal stress [{su}]"]
    else:
        cols += [column(100.0 * (x - 1.0), max(nd_x - 2, 0)), column(stress / STRESS_UNITS[su], nd_s)]
        names += ["strain [%]", f"engineering stress [{su}]"]
    path.write_text("\n".join(head + [",".join(names)] + _rows(cols, ",")) + "\n", encoding="utf-8")
    return {"format": "processed", "headers": names, "time": with_time}


WRITERS = {"comments": write_comments, "parentheses": write_parentheses, "units_row": write_units_row,
           "european": write_european, "bluehill": write_bluehill, "gbk": write_gbk, "processed": write_processed}


def allowed(mode: str) -> dict:
    """Format weights for a test: Bluehill and the GBK machine export uniaxial tests only."""
    w = {"comments": 3.0, "parentheses": 2.5, "units_row": 2.0, "european": 2.0, "bluehill": 2.0, "gbk": 0.7,
         "processed": 1.0}
    if mode != "uniaxial":
        w.pop("bluehill")
        w.pop("gbk")
    return w


def write(fmt: str, path: Path, rec: dict, rng: np.random.Generator) -> dict:
    return WRITERS[fmt](path, rec, rng)
