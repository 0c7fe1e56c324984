"""The runner on the simulated bench: FRF against the model truth; injected faults.

Faults come from the simulated bench's own fault book; "outputs off within 100 ms" is read
from the simulated 33220A drivers' command logs.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from pelvislab.acquisition.runner import prepare_session
from pelvislab.acquisition.session import SessionReader

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")
faults = pytest.importorskip("pelvislab.sim_instruments.faults")

PROTOCOL = """
schema = "pelvislab-protocol"
schema_version = 1
name = "sim-test"
[sweep]
frequencies_hz = [40.0, 100.0, 160.0, 220.0, 280.0]
drive_vpp = 0.2
settle_s = 0.05
[ultrasound]
pulses = 1000
samples = 500
[[setups]]
name = "a"
excitation = "SIAS_R_x"
transducers = { ch1 = "SIAS_R_x", ch2 = "sacrum_x" }
[[setups]]
name = "b"
excitation = "SIAS_L_x"
transducers = { ch1 = "SIPS_R_x", ch2 = "SIPS_L_x" }
"""


def run(tmp_path, **sim_options):
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    bench = sim_bench.open_simulated_bench(generators="python", **sim_options)
    events = []
    with prepare_session(protocol, tmp_path / "s.h5", bench=bench) as session:
        session.runner.subscribe(events.append)
        final = session.run()
        t0 = session.runner.started_clock_s
    return final, bench, events, t0


def output_off_after(generator, t0: float) -> float:
    """Seconds from t0 to the first output-off command the generator received after t0."""
    times = [t for t, text in generator.command_log
             if text.strip().upper() in ("OUTP OFF", "OUTP 0") and t >= t0]
    assert times, generator.command_log[-5:]
    return times[0] - t0


def test_measured_frf_matches_the_simulated_pelvis(tmp_path):
    from pelvislab.model.frf import frf
    from pelvislab.model.pelvis import default_model

    final, bench, _, _ = run(tmp_path)
    assert final.status == "completed" and final.n_done == 10
    with SessionReader(tmp_path / "s.h5") as reader:
        measured = reader.frf()
    truth = frf(default_model(), measured.frequency_hz, measured.outputs, measured.inputs)
    m = np.isfinite(measured.H)
    assert m.sum() == 20
    ratio = measured.H[m] / truth[m]
    # convention check (force phase, directions, sign): median ratio 1, phase ~0
    assert abs(np.median(ratio.real) - 1) < 0.05
    assert abs(np.degrees(np.median(np.angle(ratio)))) < 3
    # the stated uncertainty covers the error for most lines
    err = np.abs(measured.H[m] - truth[m])
    assert np.mean(err < 3 * measured.H_std[m]) > 0.8


@pytest.mark.parametrize(("fault", "expect"), [
    (faults.DigitizerTimeout(at_acquisition=3), "Timeout"),
    (faults.ScpiError(instrument="drive", at_command=24), "-222"),
    (faults.LostConnection(instrument="trigger", at_command=20), "Connection"),
])
def test_injected_fault_outputs_off_reason_recorded_data_kept(tmp_path, fault, expect):
    final, bench, events, t0 = run(tmp_path, faults=[fault])
    assert final.status == "failed", final
    assert expect.lower() in final.reason.lower() and "\n" not in final.reason
    assert bench.world.faults.fired
    fault_event = next(e for e in events if e.__class__.__name__ == "Fault")
    t_fault = t0 + fault_event.fault_t_s
    with SessionReader(tmp_path / "s.h5") as reader:
        status, reason = reader.status
        assert status == "failed" and reason == final.reason
        assert len(list(reader.steps())) == final.n_done
        if isinstance(fault, faults.DigitizerTimeout):
            assert final.n_done == 3  # the acquisitions before the fault are all kept
        assert any("ERROR" in line and "fault" in line for line in reader.log_lines())
    for gen, state in ((bench.drive, bench.world.drive), (bench.trigger, bench.world.trigger)):
        if gen is bench.trigger and isinstance(fault, faults.LostConnection):
            continue  # a lost instrument cannot be switched off (the drive still is)
        assert not state.output
        assert output_off_after(gen, t_fault) < 0.1


def test_abort_outputs_off_within_100_ms_realtime(tmp_path):
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    bench = sim_bench.open_simulated_bench(generators="python", pacing="realtime")
    with prepare_session(protocol, tmp_path / "s.h5", bench=bench) as session:
        done = {}
        thread = threading.Thread(target=lambda: done.setdefault("f", session.run()))
        thread.start()
        deadline = time.monotonic() + 20
        while bench.world.acquisitions < 2 and time.monotonic() < deadline:
            time.sleep(0.005)
        t_abort = time.monotonic()
        session.runner.abort("operator pressed STOP")
        thread.join(20)
    assert done["f"].status == "aborted"
    for gen, state in ((bench.drive, bench.world.drive), (bench.trigger, bench.world.trigger)):
        assert output_off_after(gen, t_abort) < 0.1
        assert not state.output
