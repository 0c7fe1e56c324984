"""Drive-level profile and auto drive mode in the protocol schema (v1, backwards compatible)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pelvislab.acquisition.protocol import (
    MIN_DRIVE_VPP,
    BenchLimits,
    drive_profile_vpp,
    load_protocol,
)
from tests.test_protocol_schema import base, parse, problems_of

PROFILE = [[5.0, 0.02], [20.0, 0.1], [40.0, 0.5]]


def test_profile_interpolates_log_log_and_holds_outside():
    # knots exactly; held constant outside the profile
    assert drive_profile_vpp(PROFILE, 5.0) == pytest.approx(0.02)
    assert drive_profile_vpp(PROFILE, 20.0) == pytest.approx(0.1)
    assert drive_profile_vpp(PROFILE, 40.0) == pytest.approx(0.5)
    assert drive_profile_vpp(PROFILE, 1.0) == pytest.approx(0.02)
    assert drive_profile_vpp(PROFILE, 300.0) == pytest.approx(0.5)
    # log-log: at the geometric-mean frequency, the geometric-mean level
    assert drive_profile_vpp(PROFILE, 10.0) == pytest.approx(math.sqrt(0.02 * 0.1))
    assert drive_profile_vpp(PROFILE, math.sqrt(800.0)) == pytest.approx(math.sqrt(0.05))
    # vectorised, monotone between increasing knots
    f = np.linspace(1.0, 300.0, 200)
    v = drive_profile_vpp(PROFILE, f)
    assert v.shape == f.shape and np.all(np.diff(v) >= -1e-15)
    # one point: constant
    assert drive_profile_vpp([[50.0, 0.3]], 7.0) == pytest.approx(0.3)


def test_profile_gives_each_planned_step_its_level():
    data = base()
    del data["sweep"]["drive_vpp"]
    data["sweep"]["drive_profile"] = PROFILE
    p = parse(data)
    steps = p.steps()
    by_f = {s.frequency_hz: s.drive_vpp for s in steps}
    assert by_f[5.0] == pytest.approx(0.02) and by_f[300.0] == pytest.approx(0.5)
    assert by_f[10.0] == pytest.approx(math.sqrt(0.02 * 0.1))
    assert p.sweep.drive_vpp == pytest.approx(0.5)  # the highest level (bench limit)
    assert "profile" in p.summary()


def test_plain_drive_vpp_still_works():
    p = parse(base())
    assert p.sweep.drive_mode == "fixed" and p.sweep.drive_profile == ()
    assert {s.drive_vpp for s in p.steps()} == {0.5}


def test_auto_mode_parsed():
    data = base()
    data["sweep"].update(drive_mode="auto", max_displacement_m=20e-6, min_drive_vpp=0.05)
    p = parse(data)
    assert p.sweep.drive_mode == "auto"
    assert p.sweep.max_displacement_m == pytest.approx(20e-6)
    assert p.sweep.min_drive_vpp == pytest.approx(0.05)
    assert "auto-ranging" in p.summary()


@pytest.mark.parametrize(("edit", "key", "rule"), [
    (lambda s: s.update(drive_profile=[[5.0, 0.1], [5.0, 0.2]]), "sweep.drive_profile[1]",
     "increase strictly"),
    (lambda s: s.update(drive_profile=[[40.0, 0.5], [20.0, 0.1]]), "sweep.drive_profile[1]",
     "increase strictly"),
    (lambda s: s.update(drive_profile=[[5.0, 0.1], [40.0, 3.0]]), "sweep.drive_profile[1]",
     "bench limit"),
    (lambda s: s.update(drive_profile=[[5.0, 0.001]]), "sweep.drive_profile[0]",
     "generator minimum"),
    (lambda s: s.update(drive_profile=[[-5.0, 0.1]]), "sweep.drive_profile[0]", "> 0 Hz"),
    (lambda s: s.update(drive_profile=[5.0, 0.1]), "sweep.drive_profile", "pairs"),
    (lambda s: s.update(drive_profile=[]), "sweep.drive_profile", "pairs"),
    (lambda s: s.update(drive_profile=[["5 Hz", 0.1]]), "sweep.drive_profile", "pairs"),
    (lambda s: s.update(drive_mode="loud"), "sweep.drive_mode", "must be one of"),
    (lambda s: s.update(drive_mode="auto"), "sweep.max_displacement_m", "missing"),
    (lambda s: s.update(max_displacement_m=2e-5), "sweep.max_displacement_m",
     "only used with drive_mode"),
    (lambda s: s.update(drive_mode="auto", max_displacement_m=-1.0),
     "sweep.max_displacement_m", "must be > 0"),
    (lambda s: s.update(drive_mode="auto", max_displacement_m=2e-5, min_drive_vpp=0.001),
     "sweep.min_drive_vpp", "must be >="),
    (lambda s: s.update(drive_vpp=0.001), "sweep.drive_vpp", "generator minimum"),
])
def test_drive_validation_names_key_and_rule(edit, key, rule):
    data = base()
    edit(data["sweep"])
    message = problems_of(data)
    assert f"{key}: " in message and rule in message, message


def test_profile_and_drive_vpp_together_refused():
    data = base()
    data["sweep"]["drive_profile"] = PROFILE
    message = problems_of(data)
    assert "sweep.drive_profile: give either sweep.drive_vpp or sweep.drive_profile" in message


def test_neither_drive_key_is_missing():
    data = base()
    del data["sweep"]["drive_vpp"]
    assert "sweep.drive_vpp: missing" in problems_of(data)


def test_profile_checked_against_the_bench_file_limit():
    data = base()
    del data["sweep"]["drive_vpp"]
    data["sweep"]["drive_profile"] = PROFILE
    with pytest.raises(ValueError, match=r"sweep.drive_profile\[2\]: level 0.5 .*bench limit"):
        parse(data, BenchLimits(max_drive_vpp=0.4, name="my bench"))


@pytest.mark.parametrize("name", ["face_up.toml", "face_down.toml", "demo.toml"])
def test_shipped_protocols_level_within_generator_range(name):
    from importlib import resources

    path = resources.files("pelvislab.protocols") / name
    p = load_protocol(str(path))
    levels = [s.drive_vpp for s in p.steps()]
    assert min(levels) >= MIN_DRIVE_VPP and max(levels) <= BenchLimits().max_drive_vpp


def test_record_longer_than_the_digitizer_memory_refused():
    data = base()  # 10 periods of 5 Hz = 10 000 pulses x 500 samples = 5e6: fits 8 Mi
    parse(data)
    data["ultrasound"]["samples"] = 1000  # 1e7 samples: does not (record 12 us < 200 us)
    message = problems_of(data)
    assert "sweep.periods_per_step: the longest record (10000 pulses x 1000 samples" in message
    assert "digitizer memory of 8388608 samples" in message
    parse(data, BenchLimits(max_samples_per_channel=16 * 1024 * 1024))


def test_a_floor_above_the_planned_levels_is_warned_about():
    # min_drive_vpp = 1 with drive_vpp = 0.5 passed: a step at or under the floor is never
    # repeated, so auto-ranging did nothing, unsaid
    from tests.test_protocol_schema import base, parse

    data = base()
    data["sweep"].update(drive_vpp=0.5, drive_mode="auto", max_displacement_m=20e-6,
                         min_drive_vpp=1.0)
    (note,) = [w for w in parse(data).warnings if w.startswith("sweep.min_drive_vpp:")]
    assert "above the planned level of 119 of 119 lines" in note
    data["sweep"]["min_drive_vpp"] = 0.5  # at the level: meant (a profile's floor)
    assert not [w for w in parse(data).warnings if w.startswith("sweep.min_drive_vpp:")]
