"""Discovery on single cases of the independent population (benchmarks/population), regenerated from
their seeds: records no part of esmm made, each a failure of an earlier rule, named here with the rule
that mends it. The population's own figures are the benchmark's (``make bench-discover``); these are the
cases' verdicts, which a change of the rules must not lose without saying so."""

from __future__ import annotations

import json

import numpy as np
import pytest
from esmm.pipeline.discover import discover
from esmm.pipeline.materials.terms import TERMS
from esmm.pipeline.progress import SILENT
from esmm.pipeline.tensile.files import read_tests
from esmm.pipeline.tensile.noise import quantum
from population import make_case, plan

#: (seed, case, what the case is, the rule that names its effect)
CASES = [
    (0, 157, "a Mooney-Rivlin ramp with one grip slip at a quarter of its peak force",
     "terms ranked by the gain of a positive modulus only (three I1 terms that asked for a negative modulus "
     "were tried first and the I2 terms never)"),
    (4, 102, "a relaxation test whose load cell reads 4.4 % of the peak at rest",
     "the offset alone checked when the offset with a drift fails on held-out data"),
    (4, 130, "an Ogden ramp with one grip slip, ending in a short hold",
     "a record whose part after the first loading is shorter than one block is cut in blocks over all of it"),
    (4, 276, "cycles to rising peaks with a residual stretch growing as the prestrain to the power 1.8",
     "the permanent set's exponent (without it a damage and a relaxation were kept beside the set)"),
    (7, 270, "a fibre-reinforced staircase with Schapery's stretch-dependent relaxation",
     "a strain-energy term tried in a pair with a history effect (after the relaxation, the fibre term and the "
     "stretch-dependent relaxation each halve the held-out error alone, and neither replicates across the "
     "blocks while the other's residual is left)"),
    (8, 129, "a ramp and hold whose load cell reads an offset",
     "the offset alone checked when the offset with a drift predicts held-out data better but its drift does "
     "not explain the residual's path-dependent part"),
    (18, 128, "a neo-Hookean strip pulled at two rates a decade apart, one slow relaxation time growing with the "
     "stretch", "a plain and a stretch-dependent relaxation checked at the rank of the better fit (checked behind "
     "the plain one's poor fit, the stretch-dependent one came after a load cell's drift, which took it up)"),
    (18, 114, "cycles of a tendon whose fibres are recruited by a Weibull law, the load cell reading an offset",
     "the Weibull toe (the compact Beta toe's misfit near the end of the recruitment was taken up by a relaxation, "
     "and the offset was not kept)"),
    (22, 67, "a tendon staircase whose load cell reads an offset of 3.5 % of the peak at rest",
     "the samples at rest held out in blocks of their own, each fold reading the offset from its training "
     "samples (in the always-fitted first loading, no fold held out what shows the offset, and it was rejected)"),
    (24, 60, "a toe-law tendon ramp with two grip slips, its force on a 12-bit converter's 4.88 N step",
     "the converter's step read as the grid the ramp climbs one level at a time (read as four steps, from the "
     "larger changes between the plateaus where the toe climbs fast and the slips fall, it put the noise at four "
     "times its size and no fall counted as a slip)"),
    (24, 138, "a toe-law tendon ramp with one grip slip at a third of its peak force",
     "a fit stopped by its evaluation cap above the current model's objective continued once (started from the "
     "slip's loss of extension on a law that misfits the toe, it ended worse than the model it extends, and the "
     "slip was rejected by the pre-screen)"),
    (24, 301, "Fung's quasi-linear relaxation over cycles, its force on a 12-bit converter's step",
     "the converter's step read as the grid the cycles climb one level at a time (read as four steps, the "
     "relaxation's loops were within the noise it put at four times its size)"),
]


@pytest.mark.slow
@pytest.mark.parametrize("seed, case, what, rule", CASES, ids=[f"seed{s}-case{c}" for s, c, _, _ in CASES])
def test_population_case_named_alone(tmp_path, seed, case, what, rule):
    n = 303  # the benchmark's population size and clean share (make bench-discover)
    cls, kind = plan(seed, n, 0.66)[case]
    folder = tmp_path / f"case_{case:04d}"
    truth = make_case(np.random.SeedSequence(seed).spawn(n)[case], cls, folder, kind=kind)
    tests = read_tests(sorted(str(p) for p in folder.glob("*.csv")), overrides={}, reporter=SILENT)
    res = discover(tests, n_starts=8, max_points=400, nested=False, reporter=SILENT)
    effects = [k for k in res.kept if k not in TERMS]
    if "nonlinear_viscoelastic" in effects:  # it contains the relaxation it brings in
        effects.remove("viscoelastic")
    assert effects == [truth["class"]], json.dumps({k: c.reason for k, c in res.candidates.items()}, indent=1)


@pytest.mark.slow
def test_population_clean_weibull_toe_keeps_one_toe(tmp_path):
    """A clean tendon ramp-and-cycles record whose fibres are recruited by a Weibull law (seed 21, case 2):
    nothing but the Weibull toe is kept, and the compact toe, another form of the same term, is not tried
    once it is."""
    seed, case, n = 21, 2, 303
    cls, kind = plan(seed, n, 0.66)[case]
    assert cls == "clean"
    folder = tmp_path / f"case_{case:04d}"
    truth = make_case(np.random.SeedSequence(seed).spawn(n)[case], cls, folder, kind=kind)
    assert truth["base_law"]["name"] == "toe"
    tests = read_tests(sorted(str(p) for p in folder.glob("*.csv")), overrides={}, reporter=SILENT)
    res = discover(tests, n_starts=8, max_points=400, nested=False, reporter=SILENT)
    assert res.kept == ["toeweibull"], json.dumps({k: c.reason for k, c in res.candidates.items()}, indent=1)
    assert "another form of the same term" in res.candidates["toe"].reason


@pytest.mark.slow
def test_population_converter_step_read_as_the_grid(tmp_path):
    """A force written on a 12-bit converter's step (seed 24, case 60: 4.88 N, written to 0.1 N), a toe-law
    ramp whose plateaus shorten as it stiffens and two slips: the step read is the converter's, within the
    written digit, against the generator's own chain; not the multiple the plateaus' larger changes give."""
    seed, case, n = 24, 60, 303
    cls, kind = plan(seed, n, 0.66)[case]
    folder = tmp_path / f"case_{case:04d}"
    truth = make_case(np.random.SeedSequence(seed).spawn(n)[case], cls, folder, kind=kind)
    lsb = truth["files"][0]["chain"]["lsb_N"]
    test = read_tests([str(folder / truth["files"][0]["file"])], overrides={}, reporter=SILENT)[0]
    assert quantum(np.asarray(test.force, float)) == pytest.approx(lsb, abs=0.1)
