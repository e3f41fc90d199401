"""Strain-energy terms a discovery may add: derivatives against finite differences, zero energy at rest,
the composite model by name, its Drucker check, and the stiffness tables the network builds from it."""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.errors import ConfigError
from esmm.pipeline.materials import get_model
from esmm.pipeline.materials.loading import invariants, mu_e, nominal_stress, stress_tangent
from esmm.pipeline.materials.material import Material, load_material
from esmm.pipeline.materials.stability import drucker_check
from esmm.pipeline.materials.terms import TERMS

SHAPES = {"i2exp_b": 0.7, "i1exp_b": 0.5, "gent_J": 40.0, "fexp_k2": 2.0, "toe_delta": 0.1, "toe_p": 2.5,
          "tw_eta": 0.1, "tw_k": 2.5}


def _params(term):
    return {p.name: (p.default if p.kind == "stress" else SHAPES[p.name]) for p in term.parameters}


def _points():
    lam = np.concatenate([np.linspace(0.7, 0.98, 15), np.linspace(1.02, 2.5, 30)])
    return [invariants(mode, lam) for mode in ("uniaxial", "equibiaxial", "pure_shear")]


@pytest.mark.parametrize("name", list(TERMS))
def test_term_derivatives_match_finite_differences(name):
    term = TERMS[name]
    p = _params(term)
    for I1, I2 in _points():
        h1, h2 = 1e-7 * I1, 1e-7 * I2
        w1, w2 = term.dW(I1, I2, **p)
        fd1 = (term.energy(I1 + h1, I2, **p) - term.energy(I1 - h1, I2, **p)) / (2 * h1)
        fd2 = (term.energy(I1, I2 + h2, **p) - term.energy(I1, I2 - h2, **p)) / (2 * h2)
        np.testing.assert_allclose(w1, fd1, rtol=1e-5, atol=1e-9 * max(np.max(np.abs(w1)), 1.0))
        np.testing.assert_allclose(w2, fd2, rtol=1e-5, atol=1e-9 * max(np.max(np.abs(w2)), 1.0))
        w11, w12, w22 = term.d2W(I1, I2, **p)
        g11 = (term.dW(I1 + h1, I2, **p)[0] - term.dW(I1 - h1, I2, **p)[0]) / (2 * h1)
        g22 = (term.dW(I1, I2 + h2, **p)[1] - term.dW(I1, I2 - h2, **p)[1]) / (2 * h2)
        np.testing.assert_allclose(w11, g11, rtol=1e-4, atol=1e-8 * max(np.max(np.abs(w11)), 1.0))
        np.testing.assert_allclose(w22, g22, rtol=1e-4, atol=1e-8 * max(np.max(np.abs(w22)), 1.0))
        assert np.all(w12 == 0.0)
    assert float(term.energy(3.0, 3.0, **p)) == 0.0


def test_toe_is_quadratic_then_linear_in_uniaxial_tension():
    """P = E (λ-1)²/(2δ) on the toe, E (λ - 1 - δ/2) beyond: Shearer's uniform recruitment (p = 1, the
    default, which a file without ``toe_p`` reads as)."""
    E, d = 2e6, 0.05
    m = get_model("esedf+toe")
    p = {**m.defaults(), "mu": 0.0, "A1": 0.0, "A2": 0.0, "toe_E": E, "toe_delta": d}
    lam = np.array([1.01, 1.03, 1.05, 1.08, 1.2])
    expected = np.where(lam - 1 <= d, E * (lam - 1) ** 2 / (2 * d), E * (lam - 1 - d / 2))
    np.testing.assert_allclose(nominal_stress(m, p, "uniaxial", lam), expected, rtol=1e-9)
    without = {k: v for k, v in p.items() if k != "toe_p"}
    assert m.check(without)["toe_p"] == 1.0
    np.testing.assert_allclose(nominal_stress(m, without, "uniaxial", lam), expected, rtol=1e-9)
    assert stress_tangent(m, p, "uniaxial", np.array([1.0]))[0] == pytest.approx(0.0, abs=1e-6 * E)


@pytest.mark.parametrize("shape", [0.5, 2.0, 3.7])
def test_toe_stress_is_the_integral_of_the_recruited_fraction(shape):
    """The fibre stress is E times the integral of the fraction straight, F(s) = ((s-1)/δ)^p up to 1 + δ
    and 1 beyond: integrated here by quadrature, not by the closed form."""
    from scipy import integrate

    E, d = 3e6, 0.08
    m = get_model("esedf+toe")
    p = {**m.defaults(), "mu": 0.0, "A1": 0.0, "A2": 0.0, "toe_E": E, "toe_delta": d, "toe_p": shape}
    lam = np.array([1.004, 1.02, 1.05, 1.079, 1.081, 1.15, 1.4])
    expected = [E * integrate.quad(lambda s: min((s - 1.0) / d, 1.0) ** shape, 1.0, x, points=[1 + d],
                                   epsabs=0.0, epsrel=1e-12)[0] for x in lam]
    np.testing.assert_allclose(nominal_stress(m, p, "uniaxial", lam), expected, rtol=1e-9)


@pytest.mark.parametrize("shape", [1.0, 1.7, 4.0])
def test_weibull_toe_stress_is_the_integral_of_the_recruited_fraction(shape):
    """The Weibull toe's fibre stress is E times the integral of F(s) = 1 - exp(-((s-1)/η)^k), by quadrature
    here, not by the closed form: on both sides of z = 1 (its series and its incomplete-gamma branch), and
    far into the tail, where it is E (λ - 1 - η Γ(1 + 1/k)) to rounding."""
    from scipy import integrate
    from scipy.special import gamma

    E, eta = 2e6, 0.05
    m = get_model("esedf+toeweibull")
    p = {**m.defaults(), "mu": 0.0, "A1": 0.0, "A2": 0.0, "tw_E": E, "tw_eta": eta, "tw_k": shape}
    lam = np.array([1.0005, 1.003, 1.03, 1.0499, 1.0501, 1.12, 1.4])
    expected = [E * integrate.quad(lambda s: -np.expm1(-(((s - 1.0) / eta) ** shape)), 1.0, x,
                                   epsabs=0.0, epsrel=1e-12, limit=200)[0] for x in lam]
    np.testing.assert_allclose(nominal_stress(m, p, "uniaxial", lam), expected, rtol=1e-9)
    far = nominal_stress(m, p, "uniaxial", np.array([2.5]))
    np.testing.assert_allclose(far, E * (1.5 - eta * gamma(1.0 + 1.0 / shape)), rtol=1e-12)


def test_weibull_toe_broadcasts_over_parameter_sets():
    """m parameter sets at once (shape (m, 1)) give the rows one set at a time gives."""
    term = TERMS["toeweibull"]
    I1 = invariants("uniaxial", np.linspace(1.0, 1.3, 9))[0]
    eta, k = np.array([[0.02], [0.1]]), np.array([[1.2], [5.0]])
    together = term.d2W(I1, 3.0, 1e6, eta, k)[0]
    for i in range(2):
        np.testing.assert_array_equal(together[i], term.d2W(I1, 3.0, 1e6, eta[i, 0], k[i, 0])[0])


def test_i2_term_makes_compression_stiffer_than_tension():
    m = get_model("arruda-boyce+i2exp")
    base = {"mu": 1e3, "N": 10.0}
    with_i2 = {**base, "i2exp_a": 1e3, "i2exp_b": 20.0}
    ratio = [abs(nominal_stress(m, q, "uniaxial", 0.9)) / nominal_stress(m, q, "uniaxial", 1.1)
             for q in ({**base, "i2exp_a": 0.0, "i2exp_b": 20.0}, with_i2)]
    assert ratio[1] > ratio[0] * 1.05


def test_composite_by_name_normalised_and_refused():
    m = get_model("ESEDF + toe + mooney")
    assert m.name == "esedf+mooney+toe" and get_model(m.name) is m
    assert set(m.parameter_names) >= {"mu", "N", "A1", "A2", "f", "c2", "toe_E", "toe_delta"}
    with pytest.raises(ConfigError, match="unknown strain-energy term"):
        get_model("esedf+ogden9")
    with pytest.raises(ConfigError, match="repeated"):
        get_model("esedf+toe+toe")


def test_composite_material_round_trip_and_stiffness_tables(tmp_path):
    """A discovered elastic law flows through a material file into the network's stiffness tables."""
    from esmm.pipeline.network.tables import build_tables

    m = get_model("esedf+i2exp+toe")
    params = {**m.defaults(), "i2exp_a": 2e3, "i2exp_b": 3.0, "toe_E": 5e5, "toe_delta": 0.05}
    mat = Material(model="esedf+toe+i2exp", params=params, stress_unit="kPa", name="discovered")
    path = tmp_path / "params.toml"
    path.write_text(mat.to_toml())
    back = load_material(path)
    assert back.model == "esedf+i2exp+toe"
    assert back.params["toe_delta"] == pytest.approx(0.05)
    lam = np.array([0.95, 1.0, 1.05, 1.2])
    np.testing.assert_allclose(back.mu_e(lam), mu_e(m, params, lam), rtol=1e-9)
    tables = build_tables(back, n=64)
    assert np.all(np.isfinite(tables.mu_e(np.array([1.1]))))
    # mu_e = 2 W / (λ-1)² holds for the composite energy
    W = back.uniaxial_energy(1.2)
    assert back.mu_e(1.2) == pytest.approx(2 * W / 0.2**2, rel=1e-12)


def test_drucker_check_of_terms():
    stable = get_model("arruda-boyce+gent+i2exp")
    p = {"mu": 1e3, "N": 10.0, "gent_mu": 1e3, "gent_J": 30.0, "i2exp_a": 1e3, "i2exp_b": 0.5}
    assert drucker_check(stable, p, lo=0.6, hi=2.0).stable
    # a strong Gent-Thomas log(I2) term softens until the tangent turns negative: located
    soft = get_model("arruda-boyce+i2log")
    rep = drucker_check(soft, {"mu": 10.0, "N": 1e4, "i2log_mu": 1e4}, lo=0.5, hi=3.0)
    assert not rep.stable and rep.first_failure["uniaxial"] is not None


def test_a_shaped_toe_follows_a_weibull_recruitment_that_a_uniform_one_cannot():
    """Fibres straightening at Weibull-distributed stretches (shape 3, as fitted to collagen; the stress
    integrated here by quadrature): the toe with its shape free fits the curve to a fifth of the RMS
    error of the uniform toe (p = 1), whose error lies at the toe's foot."""
    from scipy import integrate, optimize

    eta, k, E = 0.04, 3.0, 1e8
    lam = np.linspace(1.0005, 1.12, 120)
    frac = lambda s: -np.expm1(-(((s - 1.0) / eta) ** k))  # noqa: E731
    target = np.array([E * integrate.quad(frac, 1.0, x, epsabs=0.0, epsrel=1e-10)[0] for x in lam])
    m = get_model("esedf+toe")
    base = {**m.defaults(), "mu": 0.0, "A1": 0.0, "A2": 0.0}

    def rms(free_shape: bool) -> tuple[float, np.ndarray]:
        def res(q):
            p = {**base, "toe_E": q[0] * E, "toe_delta": q[1], "toe_p": q[2] if free_shape else 1.0}
            return (nominal_stress(m, p, "uniaxial", lam) - target) / target.max()
        q0 = [1.0, 0.08, 2.0] if free_shape else [1.0, 0.08]
        lo, hi = [0.1, 1e-3, 0.5][: len(q0)], [10.0, 0.5, 8.0][: len(q0)]
        r = optimize.least_squares(res, q0, bounds=(lo, hi)).fun
        return float(np.sqrt(np.mean(r**2))), r

    uniform, r1 = rms(False)
    shaped, _ = rms(True)
    assert shaped < 0.2 * uniform
    assert np.argmax(np.abs(r1)) < lam.size // 2  # the uniform toe's worst misfit is in the toe region
