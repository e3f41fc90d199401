"""The calibrate and discover reports: one self-contained report.html per run that opens in a real headless
browser without an error, the verdict first; one panel per loading mode; model − data everywhere."""

from __future__ import annotations

import numpy as np
import pytest
from esmm.pipeline.calibrate.calibration import calibrate
from esmm.pipeline.calibrate.fit import predict
from esmm.pipeline.calibrate.plots import draw_mode, mode_figure, modes
from esmm.pipeline.calibrate.report import write_outputs
from esmm.pipeline.tensile import read
from htmlkit import browser_or_skip, check_page


@pytest.fixture(scope="module")
def brain(bundled_data):
    folder = bundled_data / "tensile" / "budday2017_brain"
    tests = [read(folder / "cortex_tension_compression.csv"), read(folder / "cortex_simple_shear.csv")]
    return tests, calibrate(tests, n_starts=2)


def test_one_panel_row_per_loading_mode(brain):
    """The brain fit.png put shear γ and stretch λ on one x-axis."""
    _, cal = brain
    assert modes(cal) == ["uniaxial", "simple_shear"]
    labels = {}
    for m in modes(cal):
        fig = mode_figure(cal, m)
        labels[m] = {ax.get_xlabel() for ax in fig.axes if ax.get_xlabel()}
    assert all("γ" not in x for x in labels["uniaxial"]) and any("λ" in x for x in labels["uniaxial"])
    assert all("λ" not in x for x in labels["simple_shear"]) and any("γ" in x for x in labels["simple_shear"])


def test_the_residual_is_model_minus_data(brain):
    import matplotlib.pyplot as plt

    tests, cal = brain
    fig, axes = plt.subplots(1, 4)
    draw_mode(axes, cal, "simple_shear")
    drawn = axes[1].lines[0].get_ydata()
    t = tests[1]
    label = axes[1].get_ylabel()
    assert label.startswith("model − data [")
    fac = {"[Pa]": 1.0, "[kPa]": 1e3, "[MPa]": 1e6}[label.split()[-1]]
    expected = (predict(cal.result, t) - t.stress) / fac
    np.testing.assert_allclose(drawn, expected, rtol=1e-9, atol=1e-12)
    plt.close(fig)


def test_calibrate_report_opens_in_a_browser(brain, tmp_path):
    browser = browser_or_skip()
    tests, cal = brain
    written = write_outputs(tmp_path, cal.result, tests, calibration=cal)
    page = check_page(written["html"], browser=browser)
    assert page.problems == []
    assert len(page.images) == 2                              # one figure per loading mode
    assert page.text.index(cal.verdict.level.upper()) < page.text.index("Data and model")
    assert "determined by the data" in page.text


def test_a_failure_test_report_shows_the_strength(bundled_data, tmp_path):
    browser = browser_or_skip()
    t = read(bundled_data / "tensile" / "tendon_instron" / "failure_incubated_2.csv")
    cal = calibrate([t], n_starts=2)
    written = write_outputs(tmp_path, cal.result, [t], calibration=cal)
    page = check_page(written["html"], browser=browser)
    assert page.problems == []
    assert len(page.images) == 2                              # the mode's figure and the failure tests'
    assert "Failure tests" in page.text and "99.44 MPa" in page.text
    md = written["report"].read_text()
    assert "## Failure tests" in md and "| rupture |" in md


@pytest.mark.slow
def test_discover_report_opens_in_a_browser(run_cli, bundled_data, tmp_path):
    browser = browser_or_skip()
    src = bundled_data / "tensile" / "tendon_instron" / "relax_incubated_3_truncated.csv"
    out = tmp_path / "disc"
    code, stdout, err = run_cli("calibrate", "--discover", src, "--out", out, "--starts", "2")
    assert code == 0, err
    assert "verdict:" in stdout
    page = check_page(out / "report.html", browser=browser)
    assert page.problems == []
    assert len(page.images) == 1 and "stress vs time" not in page.text  # the figure's titles are in the image
    assert page.text.index("What the esedf model is missing") < page.text.index("In plain words")
    assert "determined by the data" in page.text and "model − data" in page.text


def test_batch_report_opens_in_a_browser(run_cli, tmp_path):
    browser = browser_or_skip()
    lam = np.linspace(1, 1.8, 40)
    for spec, mu in (("a", 100), ("b", 150)):
        (tmp_path / f"{spec}.csv").write_text("Time (s),Stretch,Nominal stress (kPa)\n" + "".join(
            f"{i * 0.1:.1f},{x:.4f},{mu * (x - 1 / x**2):.4f}\n" for i, x in enumerate(lam)))
    out = tmp_path / "batch"
    code, _, err = run_cli("calibrate", "--by", "specimen", tmp_path / "a.csv", tmp_path / "b.csv", "--out", out,
                           "--model", "arruda-boyce", "--starts", "2", "--scheduler", "serial")
    assert code == 0, err
    for html in (out / "report.html", out / "a" / "report.html"):
        page = check_page(html, browser=browser)
        assert page.problems == [], html
    assert "2 of 2 group(s) give a usable fit" in check_page(out / "report.html", browser=browser).text


def test_discover_verdict_says_why_it_is_poor():
    """Poor for undetermined parameters alone reads as noise left; a systematic residual reads as unexplained."""
    from esmm.pipeline.discover.html import verdict_of

    doc = {"base": {"nrmse": 0.01, "heldout_nrmse": 0.012}, "final": {"nrmse": 0.01, "heldout_nrmse": 0.012,
           "parameters": {"mu": {"not_identifiable": True}, "N": {}}}, "effects": [], "outcome": ""}
    level, head, reasons, _ = verdict_of(doc)
    assert level == "poor" and "records' noise" in head and "do not determine mu" in head
    assert "not everything" not in head
    level, head, reasons, _ = verdict_of({**doc, "outcome": "What is left is systematic"})
    assert level == "poor" and "not everything is explained; the data do not determine mu" in head
    level, head, _, _ = verdict_of({**doc, "final": {**doc["final"], "parameters": {}}})
    assert level == "good" and head.startswith("Good: nothing to add; what is left is the records' noise")
