"""A spring to ground found on the wrong bone, refitted on the others from its own line."""

from __future__ import annotations

from pelvislab.model.gap import GapOptions, diagnose
from pelvislab.model.pelvis import default_model
from pelvislab.tests.test_gap_support_contacts import judge_like_data


def test_an_iliolumbar_spring_found_on_the_sacrum_is_refitted_on_the_innominate(tmp_path):
    """Fresh judge-like set 1818_025 (session 50): an iliolumbar spring (L5 to the right
    iliac crest, 9.1e5 N/m) on a subject whose base parameters end at their bounds. The
    spring settled on the sacrum (gap 0.47) and a bed contact on its line was named (0.43);
    every start of the right innominate's place, and its global line search, stopped at
    gap 0.51. Refitted from the sacrum's line on the innominate it reaches 0.115, and the
    verdict and place are right."""
    rep = diagnose(judge_like_data(1818, 25, tmp_path), default_model(),
                   GapOptions(effects=("missing_ligament", "support_resonance"))).report
    best = rep["candidates"][0]
    assert rep["verdict"] == "missing_ligament", rep["verdict_reason"]
    assert best["place"] == "innominate_right to ground", best
    assert best["gap_after"] < 0.2
    assert rep["timing_s"]["ground_spring_other_bones_s"] > 0
