"""Fibre-reinforced laws of soft tissues, uniaxial tension (fibres in the loading plane).

* :class:`FibreReinforced`: the Gasser-Ogden-Holzapfel law (Holzapfel, Gasser & Ogden 2000,
  J. Elasticity 61:1; with the dispersion ``kappa`` of Gasser, Ogden & Holzapfel 2006, J. R. Soc.
  Interface 3:15): a neo-Hookean matrix and one fibre family along the load, or two symmetric
  families at +-theta to it. Off the axis the lateral stretches differ; the transverse stretch
  ``lambda_2`` is the one at which the specimen is traction-free sideways (``dW/dlambda_2 = 0``),
  so the nominal stress is ``dW/dlambda_1`` there (and, by the envelope theorem, the derivative of
  the energy along the test). Fibres carry load only while stretched (``E > 0``).
* :class:`WeibullToe`: a neo-Hookean matrix and collagen fibres along the load that are crimped
  and straighten at stretches ``s`` drawn from a shifted Weibull distribution (fibre recruitment:
  Lanir 1983, J. Biomech. 16:1; the Weibull form of Hamedzadeh, Gasser & Federico 2018). A
  straight fibre is linear elastic in its own strain ``lambda/s - 1``. With ``F`` the cumulative
  distribution of ``s``, the fibres' stress and energy per reference volume are (integrating by
  parts)

      P_f = E lambda J(lambda),   W_f = E/2 (lambda**2 J(lambda) - K(lambda)),
      J = int_1^lambda F(s)/s**2 ds,   K = int_1^lambda F(s) ds,

  which gives a toe region (fibres being recruited) turning into a linear region.
"""

from __future__ import annotations

import numpy as np

from .laws import Law


class FibreReinforced(Law):
    """``W = mu/2 (I1-3) + n k1/(2 k2) (exp(k2 E**2) - 1)``, ``E = kappa (I1-3) + (1-3 kappa)(I4-1)``.

    Parameters (``params``): ``mu``, ``k1`` [Pa]; ``k2``, ``kappa`` (0 to 1/3), ``theta`` [rad]
    (fibre angle to the load), ``families`` (1: one family; 2: two at +-theta). Uniaxial only.
    """

    name = "hgo"
    modes = ("uniaxial",)

    def parts(self, l1, l2):
        """Energy and its partial derivatives in (lambda_1, lambda_2), lambda_3 = 1/(l1 l2)."""
        with np.errstate(over="ignore", invalid="ignore"):  # far ends of the bisection's bracket
            return self._parts(l1, l2)

    def _parts(self, l1, l2):
        p = self.params
        c2, s2 = np.cos(p["theta"]) ** 2, np.sin(p["theta"]) ** 2
        kap, n = p["kappa"], p["families"]
        l3sq = (l1 * l2) ** -2.0
        i1 = l1 * l1 + l2 * l2 + l3sq
        i4 = l1 * l1 * c2 + l2 * l2 * s2
        e = kap * (i1 - 3.0) + (1.0 - 3.0 * kap) * (i4 - 1.0)
        on = e > 0.0
        ex = np.exp(np.minimum(p["k2"] * e * e, 700.0))
        wf = np.where(on, n * p["k1"] / (2.0 * p["k2"]) * (ex - 1.0), 0.0)
        dpsi = np.where(on, n * p["k1"] * e * ex, 0.0)  # d(n psi)/dE
        di1_1 = 2.0 * l1 - 2.0 * l3sq / l1
        di1_2 = 2.0 * l2 - 2.0 * l3sq / l2
        w = 0.5 * p["mu"] * (i1 - 3.0) + wf
        d1 = 0.5 * p["mu"] * di1_1 + dpsi * (kap * di1_1 + (1.0 - 3.0 * kap) * 2.0 * l1 * c2)
        d2 = 0.5 * p["mu"] * di1_2 + dpsi * (kap * di1_2 + (1.0 - 3.0 * kap) * 2.0 * l2 * s2)
        return w, d1, d2

    def lateral(self, x) -> np.ndarray:
        """The traction-free transverse stretch lambda_2 at each x (bisection on dW/dlambda_2 = 0,
        which grows monotonically with lambda_2)."""
        x = np.asarray(x, dtype=float)
        lo = np.log(x ** -0.5) - 4.0
        hi = np.log(x ** -0.5) + 4.0
        for _ in range(110):
            mid = 0.5 * (lo + hi)
            _, _, d2 = self.parts(x, np.exp(mid))
            pos = d2 > 0.0
            hi = np.where(pos, mid, hi)
            lo = np.where(pos, lo, mid)
        return np.exp(0.5 * (lo + hi))

    def _check(self, mode: str) -> None:
        if mode != "uniaxial":
            raise ValueError(f"{self.name}: uniaxial only, not {mode!r}")

    def energy(self, x, mode: str) -> np.ndarray:
        self._check(mode)
        x = np.asarray(x, dtype=float)
        return self.parts(x, self.lateral(x))[0]

    def stress(self, x, mode: str) -> np.ndarray:
        self._check(mode)
        x = np.asarray(x, dtype=float)
        return self.parts(x, self.lateral(x))[1]

    def shear_modulus(self) -> float:
        return self.params["mu"]


class WeibullToe(Law):
    """Neo-Hookean matrix plus Weibull-recruited fibres along the load (module docstring).

    Parameters (``params``): ``mu``, ``e_f`` [Pa] (fibre modulus times volume fraction); ``s0``
    (the first fibres straighten at ``1 + s0``), ``eta`` (Weibull scale, in stretch), ``k`` (Weibull
    shape, > 1). Uniaxial only. ``J`` and ``K`` are integrated by 8-point Gauss-Legendre rules:
    over the cells of a grid once (cumulated), and over the part of a cell up to each stretch.
    """

    name = "toe"
    modes = ("uniaxial",)
    #: the largest stretch integrated and the grid's step
    S_MAX, STEP = 4.0, 2e-4
    _NODES, _WEIGHTS = np.polynomial.legendre.leggauss(8)

    def __init__(self, **params: float):
        super().__init__(**params)
        a = 1.0 + self.params["s0"]
        self._s = np.arange(a, self.S_MAX + self.STEP, self.STEP)
        j, k = self._cells(self._s[:-1], self._s[1:])
        self._j = np.concatenate(([0.0], np.cumsum(j)))
        self._k = np.concatenate(([0.0], np.cumsum(k)))

    def cdf(self, s) -> np.ndarray:
        """Fraction of fibres straight at stretch s (shifted Weibull)."""
        p = self.params
        z = np.maximum(np.asarray(s, dtype=float) - 1.0 - p["s0"], 0.0) / p["eta"]
        return -np.expm1(-(z ** p["k"]))

    def _cells(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(int F/s^2, int F) over [lo, hi] elementwise."""
        half = 0.5 * (hi - lo)[:, None]
        s = 0.5 * (hi + lo)[:, None] + half * self._NODES
        f = self.cdf(s)
        return (half * (f / s ** 2) * self._WEIGHTS).sum(axis=1), (half * f * self._WEIGHTS).sum(axis=1)

    def _jk(self, x):
        x = np.asarray(x, dtype=float)
        if np.any(x > self.S_MAX):
            raise ValueError(f"{self.name}: stretch above the tabulated {self.S_MAX}")
        xs = np.maximum(x.ravel(), self._s[0])
        i = np.clip(np.searchsorted(self._s, xs, side="right") - 1, 0, self._s.size - 1)
        pj, pk = self._cells(self._s[i], xs)
        return (self._j[i] + pj).reshape(x.shape), (self._k[i] + pk).reshape(x.shape)

    def _check(self, mode: str) -> None:
        if mode != "uniaxial":
            raise ValueError(f"{self.name}: uniaxial only, not {mode!r}")

    def energy(self, x, mode: str) -> np.ndarray:
        self._check(mode)
        x = np.asarray(x, dtype=float)
        j, k = self._jk(x)
        wm = 0.5 * self.params["mu"] * (x * x + 2.0 / x - 3.0)
        return wm + 0.5 * self.params["e_f"] * (x * x * j - k)

    def stress(self, x, mode: str) -> np.ndarray:
        self._check(mode)
        x = np.asarray(x, dtype=float)
        j, _ = self._jk(x)
        return self.params["mu"] * (x - x ** -2) + self.params["e_f"] * x * j

    def shear_modulus(self) -> float:
        return self.params["mu"]
