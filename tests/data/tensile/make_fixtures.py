"""Regenerate the small tensile-file fixtures of this folder (see README.md).

Run from the repository root:  .venv/bin/python tests/data/tensile/make_fixtures.py

Every fixture is written from analytic truth: an incompressible neo-Hookean
solid, nominal stress P = MU * (lambda - lambda**-2), on a load-unload ramp;
raw channels use the geometry stated in each file (displacement =
(lambda - 1) * L0, force = P * A). The tests recompute the truth and compare.
Values are printed with 7 significant digits, so tests compare with rtol 1e-5.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
MU = 20e3          # Pa
N = 21             # samples per fixture
LAM_MAX = 1.4


def truth(n: int = N, lam_max: float = LAM_MAX):
    """(time [s], stretch, nominal stress [Pa]): a load-unload ramp at 0.1 s per sample."""
    half = (n + 1) // 2
    up = np.linspace(1.0, lam_max, half)
    lam = np.concatenate([up, up[-2::-1]])[:n]
    t = 0.1 * np.arange(n)
    return t, lam, MU * (lam - lam**-2)


def g(x: float) -> str:
    return f"{x:.7g}"


def write(name: str, text: str, encoding: str = "utf-8", newline: str = "\n", bom: bool = False) -> None:
    data = text.replace("\n", newline).encode(encoding)
    if bom:
        data = b"\xef\xbb\xbf" + data
    (HERE / name).write_bytes(data)


def main() -> None:
    t, lam, p = truth()

    # 1. Instron-Bluehill-like export: names row, units row, quoted values, raw and processed columns.
    L0, A = 25e-3, 12e-6
    rows = ["Time,Extension,Load,Tensile strain,Tensile stress", "(s),(mm),(N),(%),(MPa)"]
    for ti, li, pi in zip(t, lam, p):
        rows.append(",".join(f'"{g(v)}"' for v in (ti, (li - 1) * L0 * 1e3, pi * A, (li - 1) * 100, pi / 1e6)))
    write("instron_like.csv", "\n".join(rows) + "\n", newline="\r\n")

    # 2. ZwickRoell-like German export: ';' and decimal comma, '# key: value' geometry, units row.
    L0, W, T = 50e-3, 10e-3, 2e-3
    rows = ["# specimen: zwick-A1", "# gauge length: 50 mm", "# width: 10 mm", "# thickness: 2 mm",
            "# orientation: 45 deg", "# Prüfer: M. Muster", "Zeit;Standardweg;Standardkraft", "s;mm;N"]
    for ti, li, pi in zip(t, lam, p):
        rows.append(";".join(g(v).replace(".", ",") for v in (ti, (li - 1) * L0 * 1e3, pi * W * T)))
    write("zwick_de_semicolon.csv", "\n".join(rows) + "\n", encoding="cp1252")
    write("zwick_de_semicolon.toml", 'encoding = "cp1252"\nmode = "uniaxial"\n')

    # 3. A Chinese machine's export in GBK (like the VHB 4910 files), geometry in the sidecar.
    L0, A = 40e-3, 20e-6
    rows = ["", "时间,位移,载荷", "(s),(mm),(N)"]
    for ti, li, pi in zip(t, lam, p):
        rows.append(",".join(f'"{v:.4f}"' if k == 0 else f'"{g(v)}"'
                             for k, v in enumerate((ti, (li - 1) * L0 * 1e3, pi * A))))
    write("gbk_raw.csv", "\n".join(rows) + "\n", encoding="gbk", newline="\r\n")
    write("gbk_raw.toml", 'specimen = "gbk-1"\ngauge_length = "40 mm"\narea = "20 mm2"\nencoding = "gbk"\n'
          'tissue = "synthetic neo-Hookean, mu = 20 kPa"\n')

    # 4. No header at all: columns and units by position from the sidecar (ms, um, mN).
    L0, A = 30e-3, 22e-6
    rows = ["# no header: columns and units are in no_header.toml"]
    for ti, li, pi in zip(t, lam, p):
        rows.append("\t".join(g(v) for v in (ti * 1e3, (li - 1) * L0 * 1e6, pi * A * 1e3)))
    write("no_header.csv", "\n".join(rows) + "\n")
    write("no_header.toml", 'columns = ["time", "displacement", "force"]\nunits = ["ms", "um", "mN"]\n'
          'gauge_length = "30 mm"\narea = "22 mm2"\n')

    # 5. Processed, UTF-8 BOM, tab-delimited, stretch and kPa.
    rows = ["# mode: uniaxial", "stretch\tnominal stress [kPa]"]
    rows += [f"{g(li)}\t{g(pi / 1e3)}" for li, pi in zip(lam, p)]
    write("processed_bom_tab.csv", "\n".join(rows) + "\n", bom=True)


if __name__ == "__main__":
    main()
