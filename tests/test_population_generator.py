"""The independent test population (benchmarks/population): its physics against closed forms,
finite differences and quadrature, its acquisition chain against signal theory, its files against
esmm's reader, its reproducibility, and its independence from esmm.

Only :func:`test_files_read_back_by_esmm` and :func:`test_population_files_are_valid_inputs`
use esmm, and only its reader, to check that the written files are valid inputs.
"""

from __future__ import annotations

import ast
import hashlib
import sys
from pathlib import Path

import numpy as np
import pytest
from population import CLASSES, generate, plan
from population import acquisition as A
from population import effects as E
from population import exports as X
from population import history as H
from population import relaxation as R
from population.fibres import FibreReinforced, WeibullToe
from population.laws import ISOTROPIC, invariants
from population.protocols import KINDS
from scipy import integrate, signal
from scipy.stats import weibull_min

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "benchmarks" / "population"


# ----------------------------------------------------------------------------- independence
def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split(".")[0])
    return out


def test_generator_imports_no_esmm_and_only_numpy_scipy():
    files = sorted(PACKAGE.glob("*.py")) + [ROOT / "benchmarks" / "bench_discover_population.py"]
    assert len(files) >= 10
    allowed = set(sys.stdlib_module_names) | {"numpy", "scipy", "population"}
    for f in files:
        mods = _imports(f)
        assert not mods & {"esmm", "cli", "pipeline", "configs"}, f"{f.name} imports esmm: {mods}"
        assert mods <= allowed, f"{f.name} imports {sorted(mods - allowed)}"


# ----------------------------------------------------------------------------- base laws
LAWS = {
    "neo_hookean": ISOTROPIC["neo_hookean"](mu=2e5),
    "mooney_rivlin": ISOTROPIC["mooney_rivlin"](c10=1.5e5, c01=4e4),
    "yeoh": ISOTROPIC["yeoh"](c1=1e5, c2=-4e3, c3=600.0),
    "gent": ISOTROPIC["gent"](mu=3e5, jm=12.0),
    "demiray": ISOTROPIC["demiray"](a=5e3, b=1.7),
    "veronda_westmann": ISOTROPIC["veronda_westmann"](c1=2e3, c2=1.2),
    "arruda_boyce": ISOTROPIC["arruda_boyce"](mu=2.5e5, lam_m=2.8),
    "ogden": ISOTROPIC["ogden"](mu=[6.3e5, 1.2e3, -1e4], alpha=[1.3, 5.0, -2.0]),
    "ogden_brain": ISOTROPIC["ogden"](mu=[-60.0], alpha=[-25.0]),
    "hgo_axial": FibreReinforced(mu=1e4, k1=5e4, k2=3.0, kappa=0.0, theta=0.0, families=1),
    "hgo_angle": FibreReinforced(mu=1e4, k1=8e4, k2=2.0, kappa=0.1, theta=np.radians(30.0), families=2),
    "toe": WeibullToe(mu=1e5, e_f=8e8, s0=0.01, eta=0.02, k=2.5),
}
POINTS = {"uniaxial": [0.8, 1.1, 1.5, 2.2], "equibiaxial": [1.1, 1.4], "pure_shear": [1.2, 1.8],
          "simple_shear": [-0.4, 0.3, 0.9]}


def _uni(lam, i1):
    return 2.0 * (lam - lam ** -2)


@pytest.mark.parametrize("lam", [0.8, 1.05, 1.6, 2.4])
def test_uniaxial_stresses_match_the_published_closed_forms(lam):
    i1 = lam ** 2 + 2.0 / lam
    e = i1 - 3.0
    ab = (0.5, 1 / 20, 11 / 1050, 19 / 7000, 519 / 673750)
    want = {
        "neo_hookean": 2e5 * (lam - lam ** -2),
        "mooney_rivlin": _uni(lam, i1) * (1.5e5 + 4e4 / lam),
        "yeoh": _uni(lam, i1) * (1e5 + 2 * -4e3 * e + 3 * 600.0 * e ** 2),
        "gent": 3e5 * (lam - lam ** -2) * 12.0 / (12.0 - e),
        "demiray": 5e3 * (lam - lam ** -2) * np.exp(1.7 * e),
        "veronda_westmann": _uni(lam, i1) * (2e3 * 1.2 * np.exp(1.2 * e) - 0.5 * 2e3 * 1.2 / lam),
        "arruda_boyce": _uni(lam, i1) * 2.5e5 * sum((k + 1) * c * i1 ** k / 2.8 ** (2 * k) for k, c in enumerate(ab)),
        "ogden": sum(m * (lam ** (a - 1) - lam ** (-a / 2 - 1)) for m, a in zip([6.3e5, 1.2e3, -1e4], [1.3, 5.0, -2.0])),
    }
    for name, value in want.items():
        got = LAWS[name].stress(np.array([lam]), "uniaxial")[0]
        assert got == pytest.approx(value, rel=1e-12), name


def test_other_modes_and_fibres_match_closed_forms():
    nh, mr = LAWS["neo_hookean"], LAWS["mooney_rivlin"]
    g = np.array([0.2, 0.7])
    assert np.allclose(nh.stress(g, "simple_shear"), 2e5 * g, rtol=1e-12)  # tau = mu gamma
    assert np.allclose(mr.stress(g, "simple_shear"), 2 * (1.5e5 + 4e4) * g, rtol=1e-12)
    lam = np.array([1.2, 1.5])
    assert np.allclose(nh.stress(lam, "equibiaxial"), 2e5 * (lam - lam ** -5), rtol=1e-12)
    assert np.allclose(nh.stress(lam, "pure_shear"), 2e5 * (lam - lam ** -3), rtol=1e-12)
    # HGO with the fibres along the load: lateral symmetry, I4 = lambda^2
    h = LAWS["hgo_axial"]
    want = 1e4 * (lam - lam ** -2) + 2 * 5e4 * (lam ** 2 - 1) * np.exp(3.0 * (lam ** 2 - 1) ** 2) * lam
    assert np.allclose(h.stress(lam, "uniaxial"), want, rtol=1e-9)
    assert np.allclose(h.lateral(lam), lam ** -0.5, rtol=1e-9)


def test_toe_law_matches_quadrature_of_the_recruitment_integral():
    """P_f = E int rho(s) (lambda/s - 1) ds over the fibres already straight (Weibull rho)."""
    toe = LAWS["toe"]
    dist = weibull_min(2.5, loc=1.01, scale=0.02)
    for lam in (1.015, 1.03, 1.06, 1.1):
        pf, _ = integrate.quad(lambda s, lam=lam: dist.pdf(s) * (lam / s - 1.0), 1.01, lam, limit=200)
        want = 1e5 * (lam - lam ** -2) + 8e8 * pf
        assert toe.stress(np.array([lam]), "uniaxial")[0] == pytest.approx(want, rel=1e-6)
    assert toe.stress(np.array([1.005]), "uniaxial")[0] == pytest.approx(1e5 * (1.005 - 1.005 ** -2))


@pytest.mark.parametrize("name", sorted(LAWS))
def test_stress_is_the_derivative_of_the_energy(name):
    """Central finite differences of W along each test's path (half for the two loaded
    directions of equibiaxial tension)."""
    law = LAWS[name]
    for mode, xs in POINTS.items():
        if mode not in law.modes:
            continue
        for x in xs:
            if name.startswith(("hgo", "toe")) and x < 1.0:
                continue
            h = 1e-6
            dw = (law.energy(np.array([x + h]), mode)[0] - law.energy(np.array([x - h]), mode)[0]) / (2 * h)
            if mode == "equibiaxial":
                dw *= 0.5
            p = law.stress(np.array([x]), mode)[0]
            assert p == pytest.approx(dw, rel=2e-6, abs=1e-6 * abs(law.shear_modulus())), (name, mode, x)


def test_angled_fibres_are_traction_free_sideways():
    """The transverse stretch of the off-axis law minimizes the energy (no lateral stress)."""
    from scipy.optimize import minimize_scalar

    h = LAWS["hgo_angle"]
    for lam in (1.1, 1.3):
        best = minimize_scalar(lambda l2, lam=lam: float(h.parts(np.array([lam]), np.array([l2]))[0][0]),
                               bounds=(0.3, 2.0), method="bounded", options={"xatol": 1e-10})
        assert h.lateral(np.array([lam]))[0] == pytest.approx(best.x, rel=1e-6)


def test_invariants_of_simple_shear():
    i1, i2 = invariants(np.array([0.5]), "simple_shear")
    assert i1[0] == pytest.approx(3.25) and i2[0] == pytest.approx(3.25)


# ----------------------------------------------------------------------------- viscoelasticity
KERNELS = {
    "prony": R.Prony([0.2, 0.15], [0.5, 20.0]),
    "fung": R.FungSpectrum(0.3, 0.01, 50.0),
    "power": R.PowerLaw(0.4, 0.2, 0.3),
}


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_reduced_relaxation_functions(name):
    k = KERNELS[name]
    assert k.value(np.array([0.0]))[0] == pytest.approx(1.0, rel=1e-12)
    assert k.value(np.array([1e30]))[0] == pytest.approx(k.g_inf, rel=1e-6)
    # the antiderivative used by the convolution is one (quadrature of the value)
    for a, b in ((0.0, 0.01), (0.3, 2.0), (10.0, 100.0)):
        q, _ = integrate.quad(lambda u: float(k.value(np.array([u]))[0]), a, b, limit=200)
        assert float(k.primitive(np.array([b]))[0] - k.primitive(np.array([a]))[0]) == pytest.approx(q, rel=1e-9)


def test_fung_spectrum_is_fungs_closed_form():
    """G(t) = [1 + C (E1(t/tau2) - E1(t/tau1))] / [1 + C ln(tau2/tau1)] (Fung 1993)."""
    from scipy.special import exp1

    k = KERNELS["fung"]
    t = np.array([0.005, 0.1, 3.0, 80.0])
    want = (1 + 0.3 * (exp1(t / 50.0) - exp1(t / 0.01))) / (1 + 0.3 * np.log(5000.0))
    assert np.allclose(k.value(t), want, rtol=1e-12)


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_step_relaxation_is_g_times_the_elastic_stress(name):
    """A step of P_e over one grid step relaxes as the step's mean of G; far from the step, as G."""
    k, dt, pe1 = KERNELS[name], 1e-3, 2.5e4
    n = 200_000
    pe = np.full(n, pe1)
    pe[0] = 0.0
    out = R.hereditary(k, dt, pe)
    for i in (1, 10, 1000, 150_000):
        t = i * dt
        q, _ = integrate.quad(lambda u: float(k.value(np.array([u]))[0]), t - dt, t, limit=200)
        assert out[i] == pytest.approx(pe1 * q / dt, rel=1e-9)
    assert out[150_000] == pytest.approx(pe1 * k.value(np.array([150.0]))[0], rel=1e-5)


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_constant_rate_ramp_against_quadrature(name):
    """P_e = r t gives P(t) = r int_0^t G(u) du (fine quadrature of G itself)."""
    k, dt, r = KERNELS[name], 0.01, 3e3
    t = np.arange(5000) * dt
    out = R.hereditary(k, dt, r * t)
    for i in (1, 37, 800, 4999):
        q, _ = integrate.quad(lambda u: float(k.value(np.array([u]))[0]), 0.0, t[i], limit=400, points=[0.01, 0.05])
        assert out[i] == pytest.approx(r * q, rel=1e-8)


def test_nonlinear_forms_reduce_to_linear_qlv_without_stretch_dependence():
    """With c = 0 both nonlinear forms are QLV: the exact Maxwell recursion (another method)
    equals the convolution, and Schapery's integral equals it too."""
    rng = np.random.default_rng(1)
    dt = 0.05
    x = 1.0 + 0.3 * np.abs(np.sin(np.linspace(0, 3 * np.pi, 4000))) + 0.001 * rng.standard_normal(4000)
    pe = 1e4 * (x - x ** -2)
    k = KERNELS["prony"]
    lin = R.hereditary(k, dt, pe)
    assert np.allclose(R.strain_dependent_rate(k.g, k.tau, dt, pe, x, 0.0), lin, rtol=1e-9, atol=1e-6)
    assert np.allclose(R.schapery(k, dt, pe, x, 0.0), lin, rtol=1e-9, atol=1e-6)
    # and with c > 0 they are not (the tests can fail)
    assert not np.allclose(R.strain_dependent_rate(k.g, k.tau, dt, pe, x, 5.0), lin, rtol=1e-3)
    assert not np.allclose(R.schapery(k, dt, pe, x, 2.0), lin, rtol=1e-3)


def test_history_effects_act_only_below_a_previous_maximum_or_past_an_onset():
    x = np.concatenate([np.linspace(1, 1.5, 50), np.linspace(1.5, 1, 50)[1:], np.linspace(1, 1.8, 80)[1:]])
    nh = LAWS["neo_hookean"]
    pe, w0 = nh.stress(x, "uniaxial"), nh.energy(x, "uniaxial")
    wm = nh.energy(np.array([1.5]), "uniaxial")[0]
    og = H.mullins_pseudo_elastic(pe, w0, r=2.0, m=0.2 * wm, beta=0.1)
    assert np.allclose(og[:50], pe[:50])  # primary loading is elastic
    assert np.all(og[55:95] < pe[55:95])  # softer below the previous maximum
    xi0 = np.sqrt(2 * nh.energy(np.array([1.3]), "uniaxial")[0])
    sd = H.simo_damage(pe, w0, xi0=xi0, a=xi0, b=0.5)
    below = x[:50] < 1.3
    assert np.allclose(sd[:50][below], pe[:50][below]) and np.all(sd[:50][~below][1:] < pe[:50][~below][1:])
    ps = H.permanent_set(x, lambda v: nh.stress(v, "uniaxial"), f=0.2, q=1.0)
    assert ps[98] == 0.0 and ps[49] < pe[49]  # slack at the return, softer at the peak


# ----------------------------------------------------------------------------- acquisition chain
def _amplitude(sos, f, fs):
    n = int(fs / f * 60)
    t = np.arange(n) / fs
    y = signal.sosfilt(sos, np.sin(2 * np.pi * f * t))
    m = int(fs / f * 20)  # the last 20 periods, well past the transient
    tt, yy = t[-m:], y[-m:]
    return 2 * np.hypot(np.mean(yy * np.sin(2 * np.pi * f * tt)), np.mean(yy * np.cos(2 * np.pi * f * tt)))


@pytest.mark.parametrize("kind", A.FILTERS)
@pytest.mark.parametrize("order", [1, 2, 4])
def test_anti_aliasing_filter_has_its_minus_3db_point_at_the_cutoff(kind, order):
    """A stepped sine sweep through the filter; the -3 dB crossing is interpolated in log f."""
    fs, fc = 800.0, 7.0
    sos = A.aa_filter(kind, order, fc, fs, ripple_db=1.0)
    f = fc * np.geomspace(0.5, 2.0, 33)
    a = np.array([_amplitude(sos, v, fs) for v in f])
    db = 20 * np.log10(a)
    i = int(np.flatnonzero((db[:-1] >= -3.0103) & (db[1:] < -3.0103))[-1])
    lf = np.log(f[i]) + (np.log(f[i + 1]) - np.log(f[i])) * (db[i] + 3.0103) / (db[i] - db[i + 1])
    assert np.exp(lf) == pytest.approx(fc, rel=0.02)


def test_quantization_steps_are_span_over_two_to_the_bits():
    v = np.linspace(-0.3, 0.7, 200_001)
    for bits in (12, 16):
        q = A.quantize(v, 2.0, bits)
        steps = np.unique(np.round(np.diff(q)[np.diff(q) != 0], 15))
        assert steps.size == 1 and steps[0] == pytest.approx(2.0 / 2 ** bits, rel=1e-9)
    assert A.quantize(np.array([5.0, -5.0]), 2.0, 12).tolist() == [1.0 - 2.0 / 4096, -1.0]


def test_recorded_force_lies_on_the_converter_grid_when_quantized_at_the_output():
    ch = _chain(quantize_at="output", noise=0.0, bits=14)
    f = np.linspace(0.0, 3.0, 64_000)
    out = A.record_force(f, ch, np.random.default_rng(0))
    lsb = ch.span_N / 2 ** 14
    assert out.size == 64_000 // ch.ratio
    assert np.allclose(out / lsb, np.round(out / lsb), atol=1e-6)
    assert np.max(np.abs(out - f[ch.ratio - 1:: ch.ratio])) < 0.01 * 3.0  # a lag, no more


def _chain(**kw):
    base = dict(f_out=10.0, ratio=16, filter="butter", order=2, cutoff_of_nyquist=0.4, ripple_db=0.5, decimator="cic",
                cic_order=2, bits=16, quantize_at="adc", capacity_N=50.0, noise_sd_of_capacity=1e-5,
                pink_corner_Hz=0.1, hum_of_noise=0.0, hum_Hz=50.0, encoder_step_m=1e-7, encoder_phase=0.3,
                position="latched", velocity_ripple=0.0, ripple_Hz=1.0, velocity_noise=0.0, accel_s=0.1)
    noise = kw.pop("noise", None)
    if noise is not None:
        base["noise_sd_of_capacity"] = noise
    base.update(kw)
    return A.Chain(**base)


def _slope(x, fs, band):
    f, p = signal.welch(x, fs=fs, nperseg=2 ** 14)
    sel = (f >= band[0]) & (f <= band[1])
    return np.polyfit(np.log(f[sel]), np.log(p[sel]), 1)[0]


def test_flicker_noise_has_a_one_over_f_spectrum():
    rng = np.random.default_rng(7)
    fs = 1000.0
    pink = A.kasdin_pink(2 ** 20, rng)
    assert _slope(pink, fs, (1.0, 50.0)) == pytest.approx(-1.0, abs=0.1)
    assert _slope(rng.standard_normal(2 ** 20), fs, (1.0, 50.0)) == pytest.approx(0.0, abs=0.1)


def test_decimators_have_unit_gain_and_the_encoder_counts_steps():
    for method in ("cic", "fir"):
        taps = A.decimator_taps(method, 8, 3, 80.0, 10.0)
        assert taps.sum() == pytest.approx(1.0)
        assert np.allclose(A.decimate(np.full(800, 2.5), taps, 8), 2.5)
    p = np.linspace(0.0, 1e-5, 1001)
    c = A.encoder(p, 1e-6, 0.5)
    assert c[0] == 0.0 and set(np.round(np.diff(c) / 1e-6, 9)) <= {0.0, 1.0}



# ----------------------------------------------------------------------------- files
def _record(mode: str, stated: str, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    n = 1500
    t = np.arange(n) * 0.04
    gauge = X.measured_length(25.4e-3 if mode != "simple_shear" else 4.2e-3)
    disp = np.round(np.abs(np.sin(t / 9.0)) * 8e-3 * gauge / 25.4e-3 / 1e-7) * 1e-7
    force = np.round((1.0 + 10.0 * np.abs(np.sin(t / 9.0)) + 0.01 * rng.standard_normal(n)) / 1e-4) * 1e-4 - 1.0
    geo = {"area": {"area": X.measured_area(12.37e-6)},
           "width x thickness": {"width": X.measured_length(6.2e-3), "thickness": X.measured_length(1.99e-3)},
           "diameter": {"diameter": X.measured_length(0.399e-3)}}[stated]
    area = geo.get("area") or geo.get("width", 0) * geo.get("thickness", 0) or np.pi * geo["diameter"] ** 2 / 4
    return {"time_s": t + 12.5, "disp_m": disp, "force_N": force, "mode": mode, "specimen": f"S-{seed}",
            "gauge_length": gauge, "stated": geo, "area_stated_m2": area, "tissue": "test", "notes": "a test",
            "time_step_s": 0.04, "disp_step_m": 1e-7, "force_step_N": 1e-4, "speed_mm_per_min": 12.0}


FILE_CASES = [(fmt, mode, stated) for fmt in X.FORMATS for mode in ("uniaxial", "simple_shear")
              for stated in ("area", "width x thickness", "diameter")
              if (mode == "uniaxial" or (fmt in X.allowed(mode) and stated == "area"))]


@pytest.mark.parametrize("fmt,mode,stated", FILE_CASES)
def test_files_read_back_by_esmm(tmp_path, fmt, mode, stated):
    """Every export format, every way of stating the cross-section, units drawn at random: esmm's
    reader finds the right stretch, stress, time, gauge length and area."""
    from esmm.pipeline.tensile import read

    for seed in range(4):
        rec = _record(mode, stated, seed)
        path = tmp_path / f"{fmt}_{seed}.csv"
        info = X.write(fmt, path, rec, np.random.default_rng(seed))
        got = read(path)
        x0 = 0.0 if mode == "simple_shear" else 1.0
        assert got.mode == mode, info
        tol_x = 0.6 * rec["disp_step_m"] / rec["gauge_length"]  # written to half the encoder's step
        assert np.allclose(got.stretch, x0 + rec["disp_m"] / rec["gauge_length"], atol=tol_x), info
        # written to half the force step (processed: as stress); Bluehill: N with five decimals
        tol = 0.6 * rec["force_step_N"] if fmt == "processed" else 1e-5
        assert np.allclose(got.stress * rec["area_stated_m2"], rec["force_N"], atol=tol), info
        if got.time is not None:
            assert np.allclose(got.time, rec["time_s"] - rec["time_s"][0], atol=1e-3), info
        if fmt != "processed":
            assert got.metadata["gauge_length"] == pytest.approx(rec["gauge_length"], rel=1e-9), info
            assert got.metadata["area"] == pytest.approx(rec["area_stated_m2"], rel=1e-9), info
            assert got.force is not None and got.displacement is not None


@pytest.mark.slow
def test_population_files_are_valid_inputs(tmp_path):
    """A generated population is read by esmm without a refusal, with the truth's geometry."""
    from esmm.pipeline.tensile import read

    index = generate(11, 5, tmp_path)
    for c in index:
        import json

        truth = json.loads((tmp_path / c["case"] / "truth.json").read_text())
        for f in truth["files"]:
            got = read(tmp_path / c["case"] / f["file"])
            assert got.n == f["samples"]
            if truth["format"] != "processed":
                assert got.metadata["gauge_length"] == pytest.approx(f["gauge_length_stated_m"], rel=1e-9)
                assert got.metadata["area"] == pytest.approx(f["area_stated_m2"], rel=1e-9)


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_same_seed_same_bytes(tmp_path):
    generate(5, 3, tmp_path / "a")
    generate(5, 3, tmp_path / "b")
    a, b = _digest(tmp_path / "a"), _digest(tmp_path / "b")
    assert a == b and len(a) >= 7
    generate(6, 3, tmp_path / "c")
    c = _digest(tmp_path / "c")
    assert all(c[k] != a[k] for k in a if k.endswith("truth.json"))


def test_at_least_half_is_clean_and_clean_cases_cover_every_protocol():
    for n in (1, 7, 24, 300):
        p = plan(3, n)
        assert sum(c == "clean" for c, _ in p) >= n / 2
    p = plan(3, 300, 2 / 3)
    assert sum(c == "clean" for c, _ in p) == 200
    assert {k for c, k in p if c == "clean"} == set(KINDS)
    assert {c for c, _ in p if c != "clean"} == set(CLASSES)
    with pytest.raises(ValueError, match="half"):
        plan(3, 10, 0.4)


@pytest.mark.slow
def test_effect_parameters_make_their_class(tmp_path):
    """A generated case's truth names its class, and a clean case carries no effect."""
    from population import make_case

    seqs = np.random.SeedSequence(9).spawn(3)
    clean = make_case(seqs[0], "clean", tmp_path / "c", kind="cycles")
    assert clean["effect"] is None and clean["class"] == "clean"
    ve = make_case(seqs[1], "viscoelastic", tmp_path / "v")
    assert ve["effect"]["name"] == "viscoelastic" and ve["effect"]["size"] > 0
    slip = make_case(seqs[2], "grip_slip", tmp_path / "g")
    assert slip["files"][0]["slips_s"] and slip["effect"]["size"] > 0


def test_slack_specimen_carries_no_force_until_taut():
    el = E.Elastic(LAWS["neo_hookean"], "uniaxial", 1.0, 1.5)
    x = np.linspace(1.0, 1.5, 501)
    p = E.slack_stress({"variant": "uneven_fibre_lengths", "delta": 0.1, "spread": 0.5}, el, x)
    assert np.all(p[x <= 1.05] == 0.0) and np.all(p[x > 1.16] > 0.0)
    sharp = E.slack_stress({"variant": "sharp", "delta": 0.1, "spread": 0.5}, el, x)
    assert np.allclose(sharp, np.where(x > 1.1, LAWS["neo_hookean"].stress(x / 1.1, "uniaxial"), 0.0))


def test_scoring_counts_plain_viscoelastic_apart_for_stretch_dependent_relaxation():
    import bench_discover_population as B

    assert B.judge("nonlinear_viscoelastic", ["viscoelastic", "nonlinear_viscoelastic"])[:2] == (True, True)
    strict, lenient, cols = B.judge("nonlinear_viscoelastic", ["viscoelastic"])
    assert (strict, lenient, cols) == (False, False, [B.PLAIN_VE])
    assert B.judge("viscoelastic", ["viscoelastic", "nonlinear_viscoelastic"])[:2] == (False, True)
    assert B.judge("slack", []) == (False, False, ["nothing"])
    assert B.judge("slack", ["slack", "sensor_offset"])[:2] == (False, True)
    lo, hi = B.clopper_pearson(0, 20)
    assert lo == 0.0 and hi == pytest.approx(1 - 0.025 ** (1 / 20))  # the exact bound at k = 0


def test_scoring_takes_discontinuous_damage_mullins_as_damage_and_only_that():
    import bench_discover_population as B

    # P = (1 - D(max W0)) P_e is esmm's damage class by its equations
    assert B.judge("mullins", ["damage"], "discontinuous_damage")[:2] == (True, True)
    assert B.judge("mullins", ["mullins"], "discontinuous_damage")[:2] == (True, True)
    assert B.judge("mullins", ["damage", "viscoelastic"], "discontinuous_damage")[:2] == (False, True)
    # Ogden-Roxburgh keeps the elastic primary curve: damage is not its name; nor is Mullins Simo's damage
    assert B.judge("mullins", ["damage"], "ogden_roxburgh")[:2] == (False, False)
    assert B.judge("damage", ["mullins"], "simo1987")[:2] == (False, False)
    # the confusion columns name what was kept
    assert B.judge("mullins", ["damage"], "discontinuous_damage")[2] == ["damage"]


def test_identifiable_cases_are_also_counted_against_the_neighbouring_class():
    """``by_class_identifiable``: d_id >= 30 counts a case identifiable; ``from_neighbour`` only where its
    ``identifiability_from`` values reach 30 too (a class without a neighbour, or a variant for which the
    neighbour's name is right too: every identifiable case)."""
    import bench_discover_population as B

    def row(cls, d_id, strict, nb=None, variant=None, timed=True):
        name = "damage" if cls == "mullins" else "viscoelastic"
        return {"class": cls, "identifiability": d_id, "strict": strict, "variant": variant, "timed": timed,
                "identifiability_from": None if nb is None else {name: nb}}

    rows = [row("nonlinear_viscoelastic", 500.0, False, 12.0), row("nonlinear_viscoelastic", 80.0, True, 45.0),
            row("nonlinear_viscoelastic", 10.0, True, 2.0), row("mullins", 300.0, True),
            row("mullins", 200.0, True, 0.5, "discontinuous_damage"), row("mullins", 90.0, True, 2.0, "ogden_roxburgh"),
            row("sensor_offset", 40.0, False, 31.0), row("mullins", 70.0, False, timed=False),
            row("mullins", 5.0, False, timed=False), row("specimen_scale", 900.0, True, timed=False)]
    got = B._by_class_identifiable(rows)
    none = {"cases": 0, "strict": 0}
    assert got["nonlinear_viscoelastic"] == {"cases": 2, "strict": 1, "from_neighbour": {"cases": 1, "strict": 1},
                                             "without_time": none}
    # the curve without time is identifiable, and counted apart; one below the edge is neither
    assert got["mullins"] == {"cases": 4, "strict": 3, "from_neighbour": {"cases": 3, "strict": 2},
                              "without_time": {"cases": 1, "strict": 0}}
    assert got["sensor_offset"]["from_neighbour"] == {"cases": 1, "strict": 0}
    assert got["specimen_scale"]["without_time"] == none  # esmm reads a scale from processed curves
    assert list(got) == [c for c in B.CLASSES if c in got]


def test_integrated_time_of_white_and_ar1_noise():
    from population.cases import integrated_time

    rng = np.random.default_rng(3)
    assert integrated_time(rng.standard_normal(200_000)) == pytest.approx(1.0, abs=0.05)
    phi, e = 0.8, rng.standard_normal(400_000)
    ar = signal.lfilter([1.0], [1.0, -phi], e)
    assert integrated_time(ar) == pytest.approx((1 + phi) / (1 - phi), rel=0.05)  # AR(1): (1 + phi)/(1 - phi)


def test_detectability_is_reproduced_and_leaves_the_records_unchanged(tmp_path, monkeypatch):
    from population import cases as C

    def seq():
        return np.random.SeedSequence(11).spawn(3)[2]

    truth = C.make_case(seq(), "sensor_offset", tmp_path / "a" / "case")
    again = C.make_case(seq(), "sensor_offset", tmp_path / "b" / "case")
    d = truth["effect"]["detectability"]
    assert d == again["effect"]["detectability"] and d > 0.0
    # against a plain relaxation too (a neighbour of an offset's drift): never more than against a law alone
    d_nb = truth["effect"]["identifiability_from"]["viscoelastic"]
    assert d_nb == again["effect"]["identifiability_from"]["viscoelastic"]
    assert 0.0 <= d_nb <= truth["effect"]["identifiability"] * (1 + 1e-9)
    monkeypatch.setattr(C, "_detectability", lambda *a, **k: (None, None, {}))  # its extra noise draw taken away
    bare = C.make_case(seq(), "sensor_offset", tmp_path / "c" / "case")
    for f in truth["files"]:
        assert (tmp_path / "a" / "case" / f["file"]).read_bytes() == (tmp_path / "c" / "case" / f["file"]).read_bytes()
    assert bare["effect"]["detectability"] is None
    assert C.make_case(seq(), "clean", tmp_path / "d", kind="ramp")["effect"] is None


@pytest.mark.slow
def test_rescore_rebuilds_rows_from_the_truths_and_scores_them_again(tmp_path):
    import json

    import bench_discover_population as B

    work = tmp_path / "pop"
    index = generate(0, 5, work, clean_fraction=0.5)
    truths = {c["case"]: json.loads((work / c["case"] / "truth.json").read_text()) for c in index}
    said = {"sensor_offset": ["sensor_offset"], "clean": ["viscoelastic"], "grip_slip": [],
            "mullins": ["damage"]}
    rows = [B._row(t, {"status": "ok", "seconds": 1.0, "effects": said[t["class"]], "terms": []})
            for t in truths.values()]
    for r in rows:  # a run scored before the truths had a detectability
        r.pop("detectability")
    run = {"population": {"seed": 0, "cases": 5, "clean_fraction": 0.5, "generator_version": "2"},
           "command": "the run", **B.score(rows)}
    src, out = tmp_path / "run.json", tmp_path / "again.json"
    src.write_text(json.dumps(run))
    assert B.main(["--rescore", str(src), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["command"] == "the run" and doc["population"]["run_generator_version"] == "2"
    classes = [t["class"] for t in truths.values()]
    assert doc["clean"]["false_positives"] == classes.count("clean")  # every clean case "kept" viscoelastic
    for cls, r in zip(classes, doc["cases"]):
        if cls != "clean":
            v = truths[r["case"]]["effect"]["variant"]
            right = cls == "sensor_offset" or (cls == "mullins" and v == "discontinuous_damage")
            assert (r["strict"], r["detectability"] > 0) == (right, True)
    n_eff = len(classes) - classes.count("clean")
    assert n_eff >= 2 and sum(v["cases"] for v in doc["effects"]["by_detectability"].values()) == n_eff
    # one class rebuilt: the others keep the run's rows (here without their detectability)
    assert "mullins" in classes
    assert B.main(["--rescore", str(src), "--out", str(out), "--classes", "mullins"]) == 0
    doc = json.loads(out.read_text())
    assert doc["rescored_classes"] == ["mullins"] and "--classes mullins" in doc["rescore_command"]
    for cls, r in zip(classes, doc["cases"]):
        assert ("detectability" in r) == (cls == "mullins")
    # a second class rebuilt on that output: both classes and both commands are said
    other = next(c for c in classes if c not in ("clean", "mullins"))
    again = tmp_path / "again2.json"
    assert B.main(["--rescore", str(out), "--out", str(again), "--classes", other]) == 0
    doc = json.loads(again.read_text())
    assert doc["rescored_classes"] == ["mullins", other]
    assert [c.rsplit(" ", 1)[1] for c in doc["rescore_command"]] == ["mullins", other]
    for cls, r in zip(classes, doc["cases"]):
        assert ("detectability" in r) == (cls in ("mullins", other))
    run["cases"][0]["samples"] += 1  # records that are not the run's are refused
    src.write_text(json.dumps(run))
    with pytest.raises(SystemExit, match="other records"):
        B.main(["--rescore", str(src), "--out", str(out)])


def test_the_part_no_elastic_law_takes():
    """``_not_elastic``: a change that is a function of the stretch vanishing at the reference leaves nothing;
    on a hold (one stretch) no function of the stretch follows a decay, so at least the decay's spread about
    its mean is left."""
    from population.cases import IDENTIFY_INTERVALS, _not_elastic
    from scipy.interpolate import BSpline

    x = np.concatenate([np.linspace(1.0, 1.4, 300), np.full(200, 1.4), np.linspace(1.4, 1.0, 300)])
    knots = np.concatenate([[1.0] * 3, np.linspace(1.0, 1.4, IDENTIFY_INTERVALS + 1), [1.4] * 3])
    basis = BSpline.design_matrix(x, knots, 3).toarray() - BSpline.design_matrix(np.array([1.0]), knots, 3).toarray()
    elastic = 5.0 * (x - 1.0) ** 2 + np.sin(6.0 * (x - 1.0))
    assert _not_elastic([(elastic, basis, 2.0)]) < 1e-12 * float(np.sum(elastic ** 2))
    decay = np.zeros_like(x)
    decay[300:500] = np.exp(-np.arange(200) / 40.0)
    spread = float(np.sum((decay[300:500] - decay[300:500].mean()) ** 2))
    assert _not_elastic([(decay, basis, 1.0)]) >= spread * (1 - 1e-9)
    assert _not_elastic([(np.ones_like(x), basis, 1.0)]) > 0.0  # a constant does not vanish at the reference


def _quiet_chain():
    """A 10 Hz chain (Butterworth, FIR decimator, 16 bits) through which the neighbours' atoms are recorded."""
    return A.Chain(f_out=10.0, ratio=10, filter="butter", order=2, cutoff_of_nyquist=0.3, ripple_db=0.5,
                   decimator="fir", cic_order=2, bits=16, quantize_at="adc", capacity_N=10.0, noise_sd_of_capacity=1e-4,
                   pink_corner_Hz=0.0, hum_of_noise=0.0, hum_Hz=50.0, encoder_step_m=1e-7, encoder_phase=0.5,
                   position="latched", velocity_ripple=0.0, ripple_Hz=1.0, velocity_noise=0.0, accel_s=0.1)


def _cycles_to(peaks) -> np.ndarray:
    """Load-unload cycles from stretch 1 to each of *peaks*, 400 samples a leg."""
    legs = [np.linspace(1.0, p, 400) for p in peaks]
    return np.concatenate([np.concatenate([leg, leg[::-1]]) for leg in legs])


def _left_beside(atoms_of, knots: int, x: np.ndarray, effect) -> float:
    """What the elastic functions and the neighbour's atoms (``atoms_of``, strengths >= 0) leave of an effect's
    change on the stretch path *x*, as a fraction of what the elastic functions alone leave; a cubic law
    with its energy, through :func:`_quiet_chain`."""
    from population.cases import _elastic_basis, _not_elastic

    ch = _quiet_chain()
    pe = 4.0 * (x - 1.0) + 30.0 * (x - 1.0) ** 3
    w0 = 2.0 * (x - 1.0) ** 2 + 7.5 * (x - 1.0) ** 4
    atoms = atoms_of({"t": np.arange(x.size) * 0.01, "x": x, "common": pe, "energy": w0}, ch, 1.0)
    assert atoms.shape[1] == knots
    basis = _elastic_basis(x, 1.0, 1.0, float(x.max()), ch)
    y = A.record_force(effect(pe, w0) - pe, ch, None)
    return _not_elastic([(y, np.hstack([basis, atoms]), 1.0)], signed=basis.shape[1]) / _not_elastic(
        [(y, basis, 1.0)])


def test_the_part_neither_an_elastic_law_nor_a_plain_relaxation_takes():
    """The neighbour's d_id (``population/cases.py``, ``_relaxation_atoms``): on a two-step staircase, a plain
    relaxation whose time lies between the dictionary's is taken by the elastic functions and the relaxation
    atoms (strengths >= 0) to a part in 10^4 of what the elastic functions leave; the same relaxation with
    its time growing tenfold with the stretch (the generator's stretch-dependent rate) is not; nor is a
    stress that grows in the holds (the atoms' strengths cannot be negative), which the signed fit takes."""
    from population.cases import RELAX_TIMES, _elastic_basis, _not_elastic, _relaxation_atoms

    dt = 0.01
    t = np.arange(0.0, 200.0, dt)
    x = 1.0 + 0.1 * np.clip(t / 5.0, 0, 1) + 0.1 * np.clip((t - 100.0) / 5.0, 0, 1)
    pe = 4.0 * (x - 1.0) + 30.0 * (x - 1.0) ** 3
    ch = _quiet_chain()
    atoms = _relaxation_atoms({"t": t, "x": x, "common": pe}, ch, 1.0, (5.0, 95.0))
    assert atoms.shape[1] == RELAX_TIMES
    basis = _elastic_basis(x, 1.0, 1.0, 1.2, ch)
    both = np.hstack([basis, atoms])
    k = basis.shape[1]
    plain = A.record_force(R.hereditary(R.Prony([0.3], [7.3]), dt, pe) - pe, ch, None)
    rate = A.record_force(R.strain_dependent_rate([0.3], [7.3], dt, pe, x, np.log(10.0) / 0.2) - pe, ch, None)
    left = _not_elastic([(plain, basis, 1.0)])  # the holds' decays: no function of the stretch follows them
    assert left > 1e-3 * float(np.sum(plain ** 2))
    assert _not_elastic([(plain, both, 1.0)], signed=k) < 1e-4 * left
    assert _not_elastic([(rate, both, 1.0)], signed=k) > 0.01 * _not_elastic([(rate, basis, 1.0)])
    assert _not_elastic([(-plain, both, 1.0)], signed=k) > 0.99 * left > 1e4 * _not_elastic([(-plain, both, 1.0)])


def test_the_part_neither_an_elastic_law_nor_a_damage_takes():
    """The Mullins softening's neighbour (``population/cases.py``, ``_damage_atoms``): on cycles to rising
    peaks, Miehe's discontinuous damage (the primary loading scaled too) is taken by the elastic functions
    and the damage atoms (strengths >= 0) to a part in 10^4 of what the elastic functions leave, and so is
    Simo's damage past an onset; Ogden and Roxburgh's softening, which reloads
    to the primary curve at each new peak, is not. On cycles to one peak the same softening is taken: a
    first loading and a reloading are two curves, which an elastic law and a damage function take."""
    from population.cases import DAMAGE_KNOTS, _damage_atoms

    def left(x, effect):
        return _left_beside(_damage_atoms, DAMAGE_KNOTS, x, effect)

    rising = _cycles_to([1.1, 1.2, 1.3, 1.4])
    assert left(rising, lambda pe, w: H.mullins_discontinuous(pe, w, d_inf=0.4, eta=0.05)) < 1e-4
    assert left(rising, lambda pe, w: H.simo_damage(pe, w, xi0=0.2, a=0.3, b=0.4)) < 1e-4
    pseudo = lambda pe, w: H.mullins_pseudo_elastic(pe, w, r=1.5, m=0.02, beta=0.1)  # noqa: E731
    assert left(rising, pseudo) > 0.05
    assert left(_cycles_to([1.4, 1.4, 1.4]), pseudo) < 1e-3



def test_the_part_neither_an_elastic_law_nor_a_mullins_softening_takes():
    """The damage's neighbour (``population/cases.py``, ``_mullins_atoms``): on cycles to rising peaks,
    Ogden and Roxburgh's softening without beta (the primary curve elastic, each reloading below it by a
    function of the energy it lacks) is taken by the elastic functions and the softening atoms (strengths
    >= 0) to a part in 10^4 of what the elastic functions leave; Simo's damage and Miehe's discontinuous
    damage, which soften the primary curve at each new peak, are not. On cycles to one peak Simo's damage
    is taken: its first loading is an elastic law, and each reloading below it differs by g(W) - g(W_max),
    a non-decreasing function of the energy lacking."""
    from population.cases import MULLINS_KNOTS, _mullins_atoms

    def left(x, effect):
        return _left_beside(_mullins_atoms, MULLINS_KNOTS, x, effect)

    rising = _cycles_to([1.1, 1.2, 1.3, 1.4])
    simo = lambda pe, w: H.simo_damage(pe, w, xi0=0.2, a=0.3, b=0.4)  # noqa: E731
    assert left(rising, lambda pe, w: H.mullins_pseudo_elastic(pe, w, r=1.5, m=0.02, beta=0.0)) < 1e-4
    assert left(rising, simo) > 0.05
    assert left(rising, lambda pe, w: H.mullins_discontinuous(pe, w, d_inf=0.4, eta=0.05)) > 0.05
    assert left(_cycles_to([1.4, 1.4, 1.4]), simo) < 1e-3

@pytest.mark.slow
def test_a_slack_is_not_identifiable_and_a_misstated_area_is(tmp_path):
    """The generated truth's identifiability (``population/cases.py``, ``_detectability``): a slack on a ramp
    far out of the noise (d >> 3) is nothing an elastic law cannot take (d_id < 3); two specimens of one
    material whose stated areas differ are (d_id of the order of d)."""
    from population import make_case

    todo = plan(2, 303, 0.66)
    seqs = np.random.SeedSequence(2).spawn(303)
    seen = {"slack": 0, "specimen_scale": 0}
    for i, ((cls, kind), seq) in enumerate(zip(todo, seqs)):
        if cls not in seen or seen[cls] >= 2:
            continue
        t = make_case(seq, cls, tmp_path / f"case_{i:04d}", kind=kind)
        e = t["effect"]
        if cls == "slack" and t["protocol"]["kind"] == "ramp" and e["detectability"] > 30:
            assert e["identifiability"] < 3.0
            seen[cls] += 1
        elif cls == "specimen_scale":
            assert e["identifiability"] > 0.3 * e["detectability"] > 30
            seen[cls] += 1
        if all(v >= 2 for v in seen.values()):
            break
    assert all(v >= 1 for v in seen.values())


@pytest.mark.slow
def test_replicates_are_mounted_with_slacks_of_their_own(tmp_path):
    """A slack on replicates: each specimen is mounted with the case's slack times its own factor, and the
    slacks' differences are what no one elastic law takes (d_id of the order of d where factors differ);
    a protocol the class is not drawn on is refused."""
    from population import make_case

    seen = 0
    for k, seq in enumerate(np.random.SeedSequence(901).spawn(4)):
        t = make_case(seq, "slack", tmp_path / f"c{k}", kind="replicates")
        e, files = t["effect"], t["files"]
        assert t["protocol"]["kind"] == "replicates" and len(e["mounting"]) == 3
        assert len({f["specimen"] for f in files}) == len(files) >= 2
        f = np.asarray(e["mounting"][: len(files)])
        if np.ptp(f) > 0.2 and e["detectability"] > 100:
            assert e["identifiability"] > 0.1 * e["detectability"]
            seen += 1
    assert seen >= 1
    with pytest.raises(ValueError, match="protocol 'staircase' is not drawn for slack"):
        make_case(np.random.SeedSequence(1), "slack", tmp_path / "x", kind="staircase")


class _Draws:
    """A stand-in for the writer's generator: every uniform draw is *u* (0: a processed export with time;
    0.99: without)."""

    def __init__(self, u: float):
        self.u = u

    def uniform(self, *args, **kwargs) -> float:
        return self.u


@pytest.mark.parametrize("cls", ["viscoelastic", "nonlinear_viscoelastic"])
def test_a_relaxation_written_without_time_is_not_identifiable(tmp_path, monkeypatch, cls):
    """A file written without its time column cannot show a change in time: a relaxation's d_id and its
    neighbour's ratio count only the files with time (generator 2.8), while d, the effect known exactly,
    is the same whether the time column is written or not."""
    import population.cases as C

    truths = {}
    for u in (0.0, 0.99):
        monkeypatch.setattr(C, "write", lambda fmt, path, rec, rng, u=u: X.write("processed", path, rec, _Draws(u)))
        truths[u] = C.make_case(np.random.SeedSequence(11, spawn_key=(5,)), cls, tmp_path / str(u) / "case",
                                kind="staircase")
    timed, untimed = truths[0.0], truths[0.99]
    assert [f["export"]["time"] for f in timed["files"]] == [True]
    assert [f["export"]["time"] for f in untimed["files"]] == [False]
    assert "time" not in (tmp_path / "0.99" / "case" / untimed["files"][0]["file"]).read_text().splitlines()[3]
    assert timed["effect"]["identifiability"] > 30.0
    assert untimed["effect"]["identifiability"] == 0.0
    assert untimed["effect"]["detectability"] == pytest.approx(timed["effect"]["detectability"], rel=1e-12)
    if cls == "nonlinear_viscoelastic":
        assert untimed["effect"].get("identifiability_from", {}).get("viscoelastic", 0.0) == 0.0
