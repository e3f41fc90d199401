"""Materials, specimens and loading ranges drawn over physically plausible values.

Five families, with the laws used for them in the literature and typical ranges:

* ``elastomer`` (natural rubber, VHB, silicone; Treloar 1944; Yeoh 1993; Gent 1996): initial shear
  modulus 0.1-2 MPa, stretches to 1.5-3;
* ``gel`` (hydrogels, soft silicones such as Ecoflex): 1-100 kPa, stretches to 1.3-2.5, also
  compression;
* ``soft_tissue`` (brain, liver, fat; Budday et al. 2017, Acta Biomater. 48:319, whose brain data
  need one-term Ogden laws with |alpha| up to ~25): 0.3-20 kPa, tension to 1.05-1.3,
  compression to 0.8-0.95, simple shear to 0.1-0.4;
* ``skin_vessel`` (skin, arteries; Veronda & Westmann 1970; Holzapfel et al. 2000): 2-100 kPa matrix,
  exponential or fibre stiffening, stretches to 1.15-1.7;
* ``tendon`` (tendon fascicles, ligaments): fibre modulus 0.2-1.5 GPa, stretches to 1.04-1.12.

Stiffening parameters are drawn as a dimensionless amount of stiffening over the tested range
(e.g. ``b (I1_max - 3)`` for an exponential law), so that every law stiffens visibly but stays
finite; a draw whose stress is not monotonic over the range, or stiffens more than 40-fold, is
drawn again.
"""

from __future__ import annotations

import numpy as np

from .fibres import FibreReinforced, WeibullToe
from .laws import ISOTROPIC, Law, invariants

FAMILIES = {
    "elastomer": {"laws": {"neo_hookean": 1.0, "mooney_rivlin": 2.0, "yeoh": 2.0, "gent": 1.5, "ogden": 2.0,
                           "arruda_boyce": 0.3},
                  "mu": (1e5, 2e6), "x_max": (1.5, 3.0), "x_min": (0.7, 0.85), "gamma": (0.5, 1.5),
                  "shapes": {"tension": 6.0, "equibiaxial": 1.0, "pure_shear": 1.0, "simple_shear": 1.0},
                  "rate": (1e-3, 0.1)},
    "gel": {"laws": {"neo_hookean": 1.5, "gent": 1.0, "yeoh": 1.0, "ogden": 1.0, "mooney_rivlin": 1.0},
            "mu": (1e3, 1e5), "x_max": (1.3, 2.5), "x_min": (0.7, 0.9), "gamma": (0.3, 1.0),
            "shapes": {"tension": 4.0, "compression": 1.5, "simple_shear": 1.0}, "rate": (1e-3, 0.05)},
    "soft_tissue": {"laws": {"ogden": 2.0, "neo_hookean": 1.0, "mooney_rivlin": 1.0, "demiray": 1.5, "gent": 0.5},
                    "mu": (3e2, 2e4), "x_max": (1.05, 1.3), "x_min": (0.8, 0.95), "gamma": (0.1, 0.4),
                    "shapes": {"tension": 3.0, "compression": 1.5, "tension_compression": 1.0,
                               "simple_shear": 1.5},
                    "rate": (1e-3, 0.05)},
    "skin_vessel": {"laws": {"demiray": 1.5, "veronda_westmann": 1.0, "hgo": 2.0, "toe": 1.0, "yeoh": 1.0},
                    "mu": (2e3, 1e5), "x_max": (1.15, 1.7), "x_min": (0.9, 0.95), "gamma": (0.2, 0.4),
                    "shapes": {"tension": 5.0, "equibiaxial": 1.0}, "rate": (1e-3, 0.05)},
    "tendon": {"laws": {"toe": 3.0, "hgo": 1.0}, "mu": (1e4, 1e6), "x_max": (1.04, 1.12),
               "x_min": (0.98, 0.99), "gamma": (0.05, 0.1), "shapes": {"tension": 1.0}, "rate": (1e-3, 0.05)},
}

#: shapes of the test: (mode of the contract, reference x)
SHAPES = {
    "tension": ("uniaxial", 1.0), "compression": ("uniaxial", 1.0), "tension_compression": ("uniaxial", 1.0),
    "equibiaxial": ("equibiaxial", 1.0), "pure_shear": ("pure_shear", 1.0), "simple_shear": ("simple_shear", 0.0),
}


def loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def pick(rng: np.random.Generator, weights: dict) -> str:
    names = sorted(weights)
    p = np.array([weights[k] for k in names], dtype=float)
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def _ogden(rng, mu: float, family: str) -> Law:
    if family == "soft_tissue":
        a = float(rng.choice([-1.0, 1.0]) * rng.uniform(2.0, 25.0))
        return ISOTROPIC["ogden"](mu=[2.0 * mu / a], alpha=[a])
    n = int(rng.integers(1, 4))
    alphas = [float(rng.uniform(1.3, 6.0))]
    alphas += [float(rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 5.0)) for _ in range(n - 1)]
    share = rng.dirichlet(np.ones(n))
    return ISOTROPIC["ogden"](mu=[2.0 * mu * s / a for s, a in zip(share, alphas)], alpha=alphas)


def _isotropic(name: str, rng, mu: float, e1: float, family: str) -> Law:
    """An isotropic law of initial shear modulus ``mu``; ``e1`` = I1 - 3 at the largest stretch."""
    cls = ISOTROPIC[name]
    if name == "neo_hookean":
        return cls(mu=mu)
    if name == "mooney_rivlin":
        phi = rng.uniform(0.05, 0.6)
        return cls(c10=0.5 * mu * (1 - phi), c01=0.5 * mu * phi)
    if name == "yeoh":
        return cls(c1=0.5 * mu, c2=0.5 * mu * rng.uniform(-0.1, 0.8) / e1, c3=0.5 * mu * rng.uniform(0.0, 0.5) / e1 ** 2)
    if name == "gent":
        return cls(mu=mu, jm=e1 / rng.uniform(0.2, 0.85))
    if name == "demiray":
        return cls(a=mu, b=rng.uniform(0.2, 3.0) / e1)
    if name == "veronda_westmann":
        c2 = rng.uniform(0.2, 3.0) / e1
        return cls(c1=mu / c2, c2=c2)
    if name == "arruda_boyce":
        chain = np.sqrt((e1 + 3.0) / 3.0)
        return cls(mu=mu, lam_m=chain / rng.uniform(0.3, 0.8))
    if name == "ogden":
        return _ogden(rng, mu, family)
    raise ValueError(name)


def _fibre(name: str, rng, family: str, x_max: float) -> Law:
    if name == "toe":
        # s0 = 0: the lab zeroes the extension at a small preload, where the first fibres are just
        # straight; a start free of force would be slack (of the fibres), not a clean record.
        if family == "tendon":
            eta = rng.uniform(0.15, 0.45) * (x_max - 1)
            return WeibullToe(mu=loguniform(rng, 1e4, 1e6), e_f=loguniform(rng, 2e8, 1.5e9), s0=0.0, eta=eta,
                              k=rng.uniform(1.5, 4.0))
        eta = rng.uniform(0.2, 0.6) * (x_max - 1)
        return WeibullToe(mu=loguniform(rng, 2e3, 1e5), e_f=loguniform(rng, 2e6, 1e8), s0=0.0, eta=eta,
                          k=rng.uniform(1.5, 4.0))
    theta = 0.0 if (family == "tendon" or rng.uniform() < 0.35) else float(np.radians(rng.uniform(5.0, 45.0)))
    kappa = 0.0 if rng.uniform() < 0.5 else float(rng.uniform(0.0, 0.25))
    mu = loguniform(rng, 2e3, 1e5) if family != "tendon" else loguniform(rng, 1e4, 1e6)
    e4 = (1 - 3 * kappa) * (x_max ** 2 * np.cos(theta) ** 2 - 1) + kappa * (x_max ** 2 + 2 / x_max - 3)
    k2 = rng.uniform(0.5, 6.0) / max(e4, 1e-6) ** 2
    return FibreReinforced(mu=mu, k1=mu * loguniform(rng, 3.0, 300.0), k2=k2, kappa=kappa, theta=theta,
                           families=1 if theta == 0.0 else 2)


def acceptable(law: Law, mode: str, x_ref: float, lo: float, hi: float) -> bool:
    """Stress monotonic over [lo, hi] (a stable material) and, for isotropic laws, at most
    40-fold stiffening (the secant modulus at the far end over the initial one); a fibre law's
    stress below 1 GPa."""
    x = np.linspace(lo, hi, 400)
    p = law.stress(x, mode)
    if not np.all(np.isfinite(p)) or np.any(np.diff(p) <= 0.0):
        return False
    if law.name in ("hgo", "toe"):  # collagen stiffens by orders of magnitude by nature, but no tissue
        return bool(np.max(np.abs(p)) < 1e9)  # carries a gigapascal (tendon fails near 100 MPa)
    far = hi if abs(hi - x_ref) >= abs(lo - x_ref) else lo
    near = x_ref + 0.02 * (far - x_ref)
    k0 = law.stress(np.array([near]), mode)[0] / (near - x_ref)
    ks = law.stress(np.array([far]), mode)[0] / (far - x_ref)
    return bool(k0 > 0 and ks / k0 < 40.0)


def draw_law(rng: np.random.Generator, family: str, mode: str, x_ref: float, lo: float, hi: float,
             name: str | None = None) -> Law:
    """A law of the family (or the named one) that is acceptable over [lo, hi]."""
    fam = FAMILIES[family]
    for _ in range(200):
        nm = name or pick(rng, fam["laws"])
        if nm in ("hgo", "toe", "veronda_westmann") and mode != "uniaxial":
            continue
        if nm in ("hgo", "toe") and lo < 1.0:
            continue
        mu = loguniform(rng, *fam["mu"])
        e1 = float(max(invariants(np.array([hi, lo]), mode)[0]) - 3.0)
        law = _fibre(nm, rng, family, hi) if nm in ("hgo", "toe") else _isotropic(nm, rng, mu, max(e1, 1e-4), family)
        if acceptable(law, mode, x_ref, lo, hi):
            return law
    raise RuntimeError(f"no acceptable law for {family} {mode} on [{lo}, {hi}]")


def draw_range(rng: np.random.Generator, family: str, shape: str) -> tuple[float, float | None]:
    """(peak, opposite peak or None) of a test of this shape."""
    fam = FAMILIES[family]
    if shape == "compression":
        return float(rng.uniform(*fam["x_min"])), None
    if shape == "tension_compression":
        return float(rng.uniform(*fam["x_max"])), float(rng.uniform(*fam["x_min"]))
    if shape == "simple_shear":
        g = float(rng.uniform(*fam["gamma"]))
        return g, (-g if rng.uniform() < 0.5 else None)
    hi = float(rng.uniform(*fam["x_max"]))
    if shape == "equibiaxial":
        hi = 1.0 + 0.6 * (hi - 1.0)
    return hi, None


def draw_specimen(rng: np.random.Generator, family: str, shape: str) -> dict:
    """Geometry [m] and how the lab states its cross-section (``stated``)."""
    if shape == "simple_shear":
        side, h = rng.uniform(5e-3, 20e-3), rng.uniform(2e-3, 10e-3)
        return {"shape": "block", "gauge_length": h, "area": side * side, "stated": "area"}
    if shape in ("compression", "tension_compression") and rng.uniform() < 0.7:
        d, h = rng.uniform(5e-3, 30e-3), rng.uniform(5e-3, 20e-3)
        return {"shape": "cylinder", "gauge_length": h, "diameter": d, "area": np.pi * d * d / 4,
                "stated": str(rng.choice(["diameter", "area"]))}
    if family == "tendon" and rng.uniform() < 0.7:
        d = loguniform(rng, 0.2e-3, 8e-3)
        return {"shape": "round", "gauge_length": rng.uniform(5e-3, 60e-3), "diameter": d, "area": np.pi * d * d / 4,
                "stated": str(rng.choice(["diameter", "area"], p=[0.7, 0.3]))}
    w = rng.uniform(2e-3, 25e-3)
    t = rng.uniform(0.3e-3, 5e-3) if family != "tendon" else rng.uniform(0.3e-3, 2e-3)
    gl = rng.uniform(10e-3, 100e-3) if shape != "equibiaxial" else rng.uniform(10e-3, 40e-3)
    return {"shape": "strip", "gauge_length": gl, "width": w, "thickness": t, "area": w * t,
            "stated": str(rng.choice(["width x thickness", "area"], p=[0.6, 0.4]))}


def replicate(rng: np.random.Generator, spec: dict) -> dict:
    """Another specimen cut like ``spec`` (the same shape and way of stating it), its dimensions
    within 0.8-1.25 times the first's, as replicates of one protocol are."""
    out = dict(spec)
    for key in ("gauge_length", "width", "thickness", "diameter"):
        if key in spec:
            out[key] = spec[key] * float(np.exp(rng.uniform(np.log(0.8), np.log(1.25))))
    if "diameter" in out:
        out["area"] = np.pi * out["diameter"] ** 2 / 4
    elif "width" in out:
        out["area"] = out["width"] * out["thickness"]
    else:
        out["area"] = spec["area"] * float(np.exp(rng.uniform(np.log(0.8), np.log(1.25))))
    return out
