"""Isotropic incompressible hyperelastic laws, written from their original papers.

Every law gives its strain energy ``W`` and the nominal (first Piola-Kirchhoff) stress of four
homogeneous incompressible tests, in closed form:

* uniaxial tension/compression, stretch ``x`` = lambda: ``lambda_1 = x``, ``lambda_2 = lambda_3 = x**-0.5``;
* equibiaxial tension: ``lambda_1 = lambda_2 = x``, ``lambda_3 = x**-2`` (stress of one loaded direction);
* pure shear (planar tension): ``lambda_1 = x``, ``lambda_2 = 1``, ``lambda_3 = 1/x``;
* simple shear, ``x`` = gamma: principal stretches ``g/2 + sqrt(1 + g**2/4)``, its inverse, and 1.

For a law written in the invariants ``I1 = sum lambda_i**2``, ``I2 = sum lambda_i**-2`` with
``W1 = dW/dI1``, ``W2 = dW/dI2`` the stresses are the classical ones (Treloar 1975, *The physics of
rubber elasticity*; Ogden 1984, *Non-linear elastic deformations*):

* uniaxial     ``P = 2 (x - x**-2) (W1 + W2 / x)``
* equibiaxial  ``P = 2 (x - x**-5) (W1 + x**2 W2)``
* pure shear   ``P = 2 (x - x**-3) (W1 + W2)``
* simple shear ``tau = 2 g (W1 + W2)``

The test suite checks each against a finite-difference derivative of ``W`` along the path
(``P = dW/dx``, half of it for the two loaded directions of equibiaxial tension).

All stresses in Pa; parameters in Pa unless dimensionless. Nothing here is shared with esmm.
"""

from __future__ import annotations

import numpy as np

MODES = ("uniaxial", "equibiaxial", "pure_shear", "simple_shear")


def principal_stretches(x, mode: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three principal stretches of a homogeneous incompressible test.

    Parameters
    ----------
    x : array_like, shape (n,)
        Stretch of the loaded direction (or the amount of shear for ``simple_shear``).
    mode : str
        One of :data:`MODES`.
    """
    x = np.asarray(x, dtype=float)
    if mode == "uniaxial":
        return x, x ** -0.5, x ** -0.5
    if mode == "equibiaxial":
        return x, x, x ** -2.0
    if mode == "pure_shear":
        return x, np.ones_like(x), 1.0 / x
    if mode == "simple_shear":
        l1 = 0.5 * x + np.sqrt(1.0 + 0.25 * x * x)
        return l1, 1.0 / l1, np.ones_like(x)
    raise ValueError(f"mode {mode!r}: use one of {', '.join(MODES)}")


def invariants(x, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """(I1, I2) of the test's deformation, shape (n,) each."""
    l1, l2, l3 = principal_stretches(x, mode)
    return l1 ** 2 + l2 ** 2 + l3 ** 2, l1 ** -2 + l2 ** -2 + l3 ** -2


class Law:
    """A strain-energy function with its parameters (``params``, a dict of floats)."""

    name = "law"
    modes: tuple[str, ...] = MODES

    def __init__(self, **params: float):
        self.params = {k: float(v) if np.ndim(v) == 0 else [float(u) for u in v] for k, v in params.items()}

    def energy(self, x, mode: str) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def stress(self, x, mode: str) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def shear_modulus(self) -> float:  # pragma: no cover - interface
        """Initial shear modulus [Pa] (the slope of simple shear at gamma = 0)."""
        raise NotImplementedError

    def describe(self) -> dict:
        return {"name": self.name, "params": dict(self.params)}


class InvariantLaw(Law):
    """A law W(I1, I2); subclasses give :meth:`w` and :meth:`dw`."""

    def w(self, i1, i2):  # pragma: no cover - interface
        raise NotImplementedError

    def dw(self, i1, i2):  # pragma: no cover - interface
        raise NotImplementedError

    def energy(self, x, mode: str) -> np.ndarray:
        i1, i2 = invariants(x, mode)
        return self.w(i1, i2)

    def stress(self, x, mode: str) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        w1, w2 = self.dw(*invariants(x, mode))
        if mode == "uniaxial":
            return 2.0 * (x - x ** -2) * (w1 + w2 / x)
        if mode == "equibiaxial":
            return 2.0 * (x - x ** -5) * (w1 + x * x * w2)
        if mode == "pure_shear":
            return 2.0 * (x - x ** -3) * (w1 + w2)
        if mode == "simple_shear":
            return 2.0 * x * (w1 + w2)
        raise ValueError(f"mode {mode!r}: use one of {', '.join(MODES)}")

    def shear_modulus(self) -> float:
        w1, w2 = self.dw(np.array([3.0]), np.array([3.0]))
        return float(2.0 * (np.ravel(w1)[0] + np.ravel(w2)[0]))


def _full(v, like):
    return np.full_like(np.asarray(like, dtype=float), v)


class NeoHookean(InvariantLaw):
    """``W = mu/2 (I1 - 3)`` (Treloar 1943)."""

    name = "neo_hookean"

    def w(self, i1, i2):
        return 0.5 * self.params["mu"] * (i1 - 3.0)

    def dw(self, i1, i2):
        return _full(0.5 * self.params["mu"], i1), _full(0.0, i1)


class MooneyRivlin(InvariantLaw):
    """``W = C10 (I1 - 3) + C01 (I2 - 3)`` (Mooney 1940; Rivlin 1948)."""

    name = "mooney_rivlin"

    def w(self, i1, i2):
        return self.params["c10"] * (i1 - 3.0) + self.params["c01"] * (i2 - 3.0)

    def dw(self, i1, i2):
        return _full(self.params["c10"], i1), _full(self.params["c01"], i1)


class Yeoh(InvariantLaw):
    """``W = C1 (I1 - 3) + C2 (I1 - 3)**2 + C3 (I1 - 3)**3`` (Yeoh 1993, Rubber Chem. Technol. 66:754)."""

    name = "yeoh"

    def w(self, i1, i2):
        e = i1 - 3.0
        p = self.params
        return p["c1"] * e + p["c2"] * e ** 2 + p["c3"] * e ** 3

    def dw(self, i1, i2):
        e = i1 - 3.0
        p = self.params
        return p["c1"] + 2.0 * p["c2"] * e + 3.0 * p["c3"] * e ** 2, _full(0.0, i1)


class Gent(InvariantLaw):
    """``W = -mu Jm/2 ln(1 - (I1 - 3)/Jm)`` (Gent 1996, Rubber Chem. Technol. 69:59); locks at I1 = 3 + Jm."""

    name = "gent"

    def w(self, i1, i2):
        mu, jm = self.params["mu"], self.params["jm"]
        return -0.5 * mu * jm * np.log(1.0 - (i1 - 3.0) / jm)

    def dw(self, i1, i2):
        mu, jm = self.params["mu"], self.params["jm"]
        return 0.5 * mu * jm / (jm - i1 + 3.0), _full(0.0, i1)


class Demiray(InvariantLaw):
    """``W = a/(2b) (exp(b (I1 - 3)) - 1)`` (Demiray 1972, J. Biomech. 5:309): Fung's exponential
    stiffening written as an isotropic energy; ``a`` is the initial shear modulus."""

    name = "demiray"

    def w(self, i1, i2):
        a, b = self.params["a"], self.params["b"]
        return 0.5 * a / b * np.expm1(b * (i1 - 3.0))

    def dw(self, i1, i2):
        a, b = self.params["a"], self.params["b"]
        return 0.5 * a * np.exp(b * (i1 - 3.0)), _full(0.0, i1)


class VerondaWestmann(InvariantLaw):
    """``W = C1 (exp(C2 (I1 - 3)) - 1) - C1 C2/2 (I2 - 3)`` (Veronda & Westmann 1970, J. Biomech. 3:111,
    cat skin); initial shear modulus ``C1 C2``."""

    name = "veronda_westmann"

    def w(self, i1, i2):
        c1, c2 = self.params["c1"], self.params["c2"]
        return c1 * np.expm1(c2 * (i1 - 3.0)) - 0.5 * c1 * c2 * (i2 - 3.0)

    def dw(self, i1, i2):
        c1, c2 = self.params["c1"], self.params["c2"]
        return c1 * c2 * np.exp(c2 * (i1 - 3.0)), _full(-0.5 * c1 * c2, i1)


#: The five coefficients of the series of the inverse Langevin function (Arruda & Boyce 1993,
#: J. Mech. Phys. Solids 41:389).
_AB_C = (0.5, 1.0 / 20.0, 11.0 / 1050.0, 19.0 / 7000.0, 519.0 / 673750.0)


class ArrudaBoyce(InvariantLaw):
    """The eight-chain model in its five-term series,
    ``W = mu sum_i C_i / lam_m**(2i - 2) (I1**i - 3**i)`` (Arruda & Boyce 1993)."""

    name = "arruda_boyce"

    def w(self, i1, i2):
        mu, lm = self.params["mu"], self.params["lam_m"]
        return mu * sum(c / lm ** (2 * k) * (i1 ** (k + 1) - 3.0 ** (k + 1)) for k, c in enumerate(_AB_C))

    def dw(self, i1, i2):
        mu, lm = self.params["mu"], self.params["lam_m"]
        w1 = mu * sum((k + 1) * c / lm ** (2 * k) * i1 ** k for k, c in enumerate(_AB_C))
        return w1 + 0.0 * i1, _full(0.0, i1)


class Ogden(Law):
    """``W = sum_p mu_p/alpha_p (l1**alpha_p + l2**alpha_p + l3**alpha_p - 3)`` (Ogden 1972, Proc. R.
    Soc. A 326:565); initial shear modulus ``sum_p mu_p alpha_p / 2``.

    Stresses (Ogden 1984): uniaxial ``sum mu_p (x**(a-1) - x**(-a/2-1))``; equibiaxial
    ``sum mu_p (x**(a-1) - x**(-2a-1))``; pure shear ``sum mu_p (x**(a-1) - x**(-a-1))``; simple shear
    ``sum mu_p (l**a - l**-a) / (l + 1/l)`` with ``l = g/2 + sqrt(1 + g**2/4)``.
    """

    name = "ogden"

    def _terms(self):
        return zip(self.params["mu"], self.params["alpha"])

    def energy(self, x, mode: str) -> np.ndarray:
        l1, l2, l3 = principal_stretches(x, mode)
        return sum(m / a * (l1 ** a + l2 ** a + l3 ** a - 3.0) for m, a in self._terms())

    def stress(self, x, mode: str) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if mode == "uniaxial":
            return sum(m * (x ** (a - 1) - x ** (-0.5 * a - 1)) for m, a in self._terms())
        if mode == "equibiaxial":
            return sum(m * (x ** (a - 1) - x ** (-2.0 * a - 1)) for m, a in self._terms())
        if mode == "pure_shear":
            return sum(m * (x ** (a - 1) - x ** (-a - 1)) for m, a in self._terms())
        if mode == "simple_shear":
            lam = 0.5 * x + np.sqrt(1.0 + 0.25 * x * x)
            return sum(m * (lam ** a - lam ** -a) for m, a in self._terms()) / (lam + 1.0 / lam)
        raise ValueError(f"mode {mode!r}: use one of {', '.join(MODES)}")

    def shear_modulus(self) -> float:
        return float(sum(0.5 * m * a for m, a in self._terms()))


ISOTROPIC = {c.name: c for c in (NeoHookean, MooneyRivlin, Yeoh, Gent, Demiray, VerondaWestmann, ArrudaBoyce, Ogden)}
