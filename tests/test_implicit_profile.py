"""scripts/implicit_profile.py: a variant's stepper options reach the stepper."""

from __future__ import annotations

from scriptkit import load_script


def test_a_variants_keys_win_over_the_scenes():
    """The run's setup passes ``factor_matrix`` and ``iteration`` from the scene; a variant that sets them
    (``--variant exact:factor_matrix=exact``) must get its own, not the scene's."""
    make = load_script("implicit_profile").stepper_with({"factor_matrix": "exact", "iteration": "newton"})
    stepper = make(step=0.01, factor_matrix="bound", iteration="quasi-newton")
    assert stepper.factor_matrix == "exact" and stepper.iteration == "newton"
    assert stepper.step == 0.01
