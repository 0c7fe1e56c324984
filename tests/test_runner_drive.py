"""Drive-level profile and auto-ranging in the runner: levels used, recorded and divided out.

The FRF is a ratio, so a step measured at a lower drive level must give the same FRF: the
force phasor of each step comes from the level actually set on the generator.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pelvislab.acquisition.runner import (
    AUTO_RANGE_LOST_STEP,
    AUTO_RANGE_MARGIN,
    AUTO_RANGE_UNKNOWN_STEP,
    auto_range_level,
    force_phasor,
    motion_amplitude_m,
    prepare_session,
)
from pelvislab.acquisition.session import SessionReader

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")

HEAD = """
schema = "pelvislab-protocol"
schema_version = 1
name = "drive-test"
[ultrasound]
samples = 500
[[setups]]
name = "a"
excitation = "SIAS_R_x"
transducers = { ch1 = "SIAS_R_x", ch2 = "sacrum_x" }
"""


def test_motion_amplitude_uses_phasor_or_half_peak_to_peak():
    assert motion_amplitude_m(3e-6 + 4e-6j, None) == pytest.approx(5e-6)
    d = np.array([0.0, 1e-5, np.nan, -1e-5])
    assert motion_amplitude_m(1e-6, d) == pytest.approx(1e-5)
    assert math.isnan(motion_amplitude_m(None, None))


def test_auto_range_lowers_by_the_measured_over_limit_ratio():
    lower, why = auto_range_level([40e-6, 1e-6], [None, None], [0.0, 0.0], 0.5, 20e-6, 0.02)
    assert lower == pytest.approx(0.5 * 20 / 40 * AUTO_RANGE_MARGIN)
    assert "motion" in why
    # within the limit and no echo lost: keep
    assert auto_range_level([10e-6], [None], [0.0], 0.5, 20e-6, 0.02) == (None, "")
    # floored, and a step already at the floor is not repeated
    lower, _ = auto_range_level([4e-3], [None], [0.0], 0.5, 20e-6, 0.02)
    assert lower == pytest.approx(0.02)
    assert auto_range_level([4e-3], [None], [0.0], 0.02, 20e-6, 0.02) == (None, "")


def test_auto_range_on_lost_echoes_with_large_or_unknown_motion():
    # every echo lost, no phasor: motion unknown -> fixed step down
    lower, why = auto_range_level([None], [None], [1.0], 2.0, 20e-6, 0.02)
    assert lower == pytest.approx(2.0 * AUTO_RANGE_UNKNOWN_STEP) and "unknown" in why
    # echoes lost while moving more than half the limit
    lower, _ = auto_range_level([15e-6], [None], [0.3], 0.5, 20e-6, 0.02)
    assert lower == pytest.approx(0.5 * AUTO_RANGE_LOST_STEP)
    # echoes lost on a channel that barely moves (e.g. a weak echo): not a motion problem
    assert auto_range_level([1e-6], [None], [0.3], 0.5, 20e-6, 0.02) == (None, "")


def run(tmp_path, sweep: str):
    protocol = tmp_path / "p.toml"
    protocol.write_text(HEAD + "[sweep]\n" + sweep)
    bench = sim_bench.open_simulated_bench(generators="python")
    with prepare_session(protocol, tmp_path / "s.h5", bench=bench) as session:
        final = session.run()
    assert final.status == "completed", final
    with SessionReader(tmp_path / "s.h5") as reader:
        steps = list(reader.steps(with_echoes=False))
        measured = reader.frf()
        log = reader.log_lines()
    return bench, steps, measured, log


def volt_commands(bench) -> list[float]:
    out = []
    for _, text in bench.drive.command_log:
        head, _, arg = text.strip().partition(" ")
        if head.upper() in ("VOLT", "VOLTAGE", "VOLT:AMPL") and arg:
            out.append(float(arg))
        elif head.upper().startswith("APPL"):
            out.append(float(arg.split(",")[1]))
    return out


def assert_frf_matches_model(measured, tolerance: float = 0.1) -> None:
    from pelvislab.model.frf import frf
    from pelvislab.model.pelvis import default_model

    truth = frf(default_model(), measured.frequency_hz, measured.outputs, measured.inputs)
    m = np.isfinite(measured.H)
    assert m.any()
    rel = np.abs(measured.H[m] / truth[m] - 1)
    assert np.all(rel < tolerance), rel


def test_profile_levels_are_set_recorded_and_divided_out(tmp_path):
    bench, steps, measured, _ = run(tmp_path, """
frequencies_hz = [40.0, 160.0]
drive_profile = [[40.0, 0.1], [160.0, 0.4]]
periods_per_step = 10
""")
    levels = {s.frequency_hz: s.drive_vpp for s in steps}
    assert levels == pytest.approx({40.0: 0.1, 160.0: 0.4})
    assert {0.1, 0.4} <= {round(v, 6) for v in volt_commands(bench)}
    for s in steps:  # the force phasor is that of the level used
        expected = force_phasor(s.frequency_hz, s.drive_vpp,
                                complex(bench.config.drive_newton_per_volt))
        assert s.force_phasor_n == pytest.approx(expected)
    assert_frf_matches_model(measured)


def test_auto_mode_repeats_a_too_large_step_lower_and_the_frf_still_matches(tmp_path):
    # 40 Hz at 0.5 Vpp moves SIAS_R_x ~14 um (amplitude): over a 2 um limit
    bench, steps, measured, log = run(tmp_path, """
frequencies_hz = [40.0]
drive_vpp = 0.5
drive_mode = "auto"
max_displacement_m = 2e-6
periods_per_step = 10
""")
    (step,) = steps
    assert step.drive_vpp < 0.5 * 0.2  # lowered by about limit/measured x margin
    assert step.extra["drive_planned_vpp"] == pytest.approx(0.5)
    assert int(step.extra["drive_attempts"]) == 2
    assert step.extra["drive_rejected_vpp"] == pytest.approx(0.5)
    assert max(abs(c.phasor_m) for c in step.channels) < 2e-6
    assert volt_commands(bench)[-1] == pytest.approx(step.drive_vpp, rel=1e-3)
    assert any("repeated at" in line for line in log)
    assert step.force_phasor_n == pytest.approx(
        force_phasor(40.0, step.drive_vpp, complex(bench.config.drive_newton_per_volt)))
    assert_frf_matches_model(measured)


def test_auto_mode_keeps_a_step_within_the_limit(tmp_path):
    bench, steps, _, log = run(tmp_path, """
frequencies_hz = [160.0]
drive_vpp = 0.2
drive_mode = "auto"
max_displacement_m = 20e-6
periods_per_step = 10
""")
    (step,) = steps
    assert step.drive_vpp == pytest.approx(0.2)
    assert int(step.extra["drive_attempts"]) == 1
    assert not any("repeated at" in line for line in log)


def test_better_record_prefers_fewer_lost_echoes_then_motion_within_the_limit():
    from pelvislab.acquisition.runner import better_record
    from pelvislab.acquisition.session import ChannelData, StepData

    def step(lost: float, ok: bool, amp: float) -> StepData:
        point = None
        c = ChannelData(name="ch1", codes=np.zeros((1, 1), np.int8),
                        trigger_offset_s=np.zeros(1), sample_rate_hz=1.0, prf_hz=1.0,
                        delay_s=0.0, volts_per_count=1.0, volts_offset=0.0,
                        speed_of_sound_m_s=1540.0, output=point, phasor_m=amp,
                        quality={"ok": ok, "lost_fraction": lost})
        return StepData("a", 10.0, point, 0.0, [c], 1.0)

    high_lost, low_partly = step(1.0, False, 0.0), step(0.47, False, 30e-6)
    assert better_record(high_lost, low_partly, 20e-6) is low_partly
    big, small = step(0.0, True, 40e-6), step(0.0, True, 5e-6)
    assert better_record(big, small, 20e-6) is small
    assert better_record(small, step(0.0, True, 2e-6), 20e-6) is small  # tie: first
