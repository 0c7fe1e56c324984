"""A global effect is fitted from its own starts too, and a named effect that leaves the
held-out lines above the noise is refitted under the other dashpot reading (issue 10).

Judge-like set 9696_005 (``tests/judge_like_generator.py``, written without reading the
diagnosis), ``unexplained`` in session 32: hysteretic damping of eq. 7.2, f_c = 0.67, on
a subject whose sacroiliac dashpots act at their own points (c_sij_L 1636 N s/m, the
"points" reading). The base fit kept the model's midpoint reading and took c_sij_L to
4454 N s/m, absorbing part of the effect; the screen, with the base frozen there, put
f_c near 0, and the joint fit from there stayed at the base's fitted-line chi2.

* The joint fit under midpoint from the screened f_c ended at held-out gap 2.53 (the
  base fit's 2.91); from eq. 7.2's own start f_c = 5 with the base fit it reaches 0.70
  (f_c 0.45; 1.81 against the base the whole diagnosis adopts): named, but above the
  noise.
* Under the "points" reading the same effect reaches the noise (gap 0.0, f_c 0.66).
"""

import numpy as np
import pytest

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process


@pytest.fixture(scope="module")
def hysteretic_set(tmp_path_factory):
    path = tmp_path_factory.mktemp("j9696") / "set_9696_005.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([9696, 5])), path)
    assert truth["effect"] == "hysteretic_damping" and truth["variant"] == "eq7.2"
    assert truth["subject"]["dashpot_lever"] == "points"
    return path, truth


def test_global_effect_found_from_own_start_and_other_reading(hysteretic_set):
    path, truth = hysteretic_set
    effects = ["hysteretic_damping", "frequency_dependent_stiffness",
               "sensor_misorientation", "added_mass"]
    report = diagnose_in_fresh_process(path, effects=effects)
    assert report["verdict"] == "hysteretic_damping", report["verdict_reason"]
    assert report["base_fit"]["dashpot_lever"] == "points"
    assert report["base_fit"]["dashpot_lever_choice"].startswith(
        "points: chosen after the effects")
    # every effect refitted under the new reading, so that the report still gives each
    # one's gap after (three of them were before session 33)
    assert sorted(c["effect"] for c in report["candidates"]) == sorted(effects)
    cand = report["candidates"][0]
    assert cand["effect"] == "hysteretic_damping"
    assert cand["variant"].startswith("eq7.2")
    assert cand["gap_after"] < 0.2
    assert abs(cand["params"]["f_c"] / truth["parameters"]["f_c"] - 1) < 0.05
    # the range the data do not exclude holds the truth
    (ne,) = [e for e in report["not_excluded"] if e["parameter"] == "f_c"]
    assert ne["low"] <= truth["parameters"]["f_c"] <= ne["high"]


def test_own_start_joint_fit_under_the_chosen_reading(hysteretic_set):
    """The joint-fit stage alone: eq. 7.2 under the model's midpoint reading, fitted from
    the base fit with its screened f_c and with its own starts."""
    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model import gap
    from pelvislab.model.pelvis import default_model

    path, _truth = hysteretic_set
    frf = read_frf(path)
    data = gap.prepare_data(frf.frequency_hz, frf.H, frf.H_std, frf.outputs, frf.inputs)
    model = default_model()
    assert model.dashpot_lever == "midpoint"
    opt = gap.GapOptions(effects=("hysteretic_damping",), jobs=1)
    ctx = gap._context(model, data)
    held_lines = (np.arange(data.frequency_hz.size) % opt.holdout_every
                  ) == opt.holdout_offset % opt.holdout_every
    fit = gap._Lines.build(ctx, data, ~held_lines)
    held = gap._Lines.build(ctx, data, held_lines)
    base = gap.fit_base(fit, ctx.base.nominal.copy(), ctx.base.names, opt)
    s = gap._stages(data, gap._Reading(model, ctx, fit, held, base), opt, held_lines, {})
    by_variant, spring_starts = gap._screen_stage(
        s, gap.candidate_library(ctx, opt.effects))
    results = gap._joint_fit_stage(s, by_variant, spring_starts)
    eq72 = [r for r in results if r.candidate.variant.startswith("eq7.2")]
    assert eq72
    best = min(eq72, key=lambda r: r.chi2_fitted)
    # base gap on the held-out lines about 2.9 (this base fit, not the refit the whole
    # diagnosis adopts); from the screened f_c alone the fit stayed there
    assert s.gap_before > 2.0
    assert best.gap_after < 1.0
    assert 0.3 < best.u[0] < 0.6
