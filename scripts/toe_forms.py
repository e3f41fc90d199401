#!/usr/bin/env python3
"""How closely each of esmm's two toe terms follows a curve of Weibull-recruited fibres.

Usage::

    .venv/bin/python scripts/toe_forms.py [--draws 40] [--seed 0] [--json OUT]

Each draw is a uniaxial tension curve of the independent population's ``WeibullToe`` law
(benchmarks/population/fibres.py: a neo-Hookean matrix and fibres along the load that straighten at
Weibull-distributed stretches, each linear in its own strain), drawn by the population's own draw
(``benchmarks/population/draws.py``) for its two families with that law, tendon and skin/vessel, at 400
stretches. Each curve is fitted by least squares (nine starts) with a neo-Hookean matrix plus one of the
two toes, ``toe`` (the Beta(p, 1) recruitment, compact) and ``toeweibull``, their stresses evaluated by
esmm's own terms; the misfit printed is the rms residual in per cent of the curve's peak stress. No noise:
this is the law's misfit alone. docs/design/model.md, "Why a second toe", quotes it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from esmm.pipeline.materials import get_model  # noqa: E402
from esmm.pipeline.materials.loading import nominal_stress  # noqa: E402
from population.draws import FAMILIES, _fibre  # noqa: E402
from population.fibres import WeibullToe  # noqa: E402

#: the term's modulus and its two shape parameters, in the order fitted
FORMS = {"toe": ("toe_E", "toe_delta", "toe_p"), "toeweibull": ("tw_E", "tw_eta", "tw_k")}


def draw(rng: np.random.Generator, family: str) -> tuple[WeibullToe, float]:
    """A Weibull-toe law and its largest stretch, drawn as the population draws them for *family*."""
    x_max = float(rng.uniform(*FAMILIES[family]["x_max"]))
    return _fibre("toe", rng, family, x_max), x_max


def misfit(x: np.ndarray, P: np.ndarray, form: str) -> float:
    """The rms residual of the best fit of a neo-Hookean matrix plus toe *form*, per cent of max |P|."""
    model = get_model(f"esedf+{form}")
    names = FORMS[form]
    fixed = {**model.defaults(), "mu": 0.0, "A1": 0.0, "A2": 0.0}
    scale = float(np.abs(P).max())
    span = float(x[-1] - 1.0)

    def stress(q):
        mu, E, a, b = np.exp(q)
        p = {**fixed, names[0]: E, names[1]: a, names[2]: b}
        return mu * (x - x ** -2) + nominal_stress(model, p, "uniaxial", x)

    best = np.inf
    for a0 in (0.2, 0.5, 1.0):
        for b0 in (1.5, 2.0, 4.0):
            q0 = np.log([P[-1] / (10 * span), P[-1] / span, a0 * span, b0])
            fit = least_squares(lambda q: (stress(q) - P) / scale, q0)
            best = min(best, float(np.sqrt(2 * fit.cost / x.size)))
    return 100.0 * best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    for i in range(args.draws):
        family = "tendon" if i % 2 else "soft tissue"
        law, x_max = draw(rng, "tendon" if i % 2 else "skin_vessel")
        x = np.linspace(1.0, x_max, 400)
        P = law.stress(x, "uniaxial")
        rows.append({"family": family, "x_max": x_max, "k": law.params["k"],
                     **{form: misfit(x, P, form) for form in FORMS}})
        print(f"{family:11s} stretch to {x_max:.3f}, Weibull shape {law.params['k']:.2f}: rms misfit "
              + ", ".join(f"{form} {rows[-1][form]:.3f} %" for form in FORMS))
    for form in FORMS:
        v = [r[form] for r in rows]
        print(f"{form}: median {np.median(v):.3f} %, range {min(v):.3f}-{max(v):.3f} % of the peak stress")
    if args.json is not None:
        args.json.write_text(json.dumps({"command": "python scripts/toe_forms.py " + " ".join(argv or sys.argv[1:]),
                                         "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
