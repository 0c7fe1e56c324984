"""Runner control on a small test bench: events, FRF values, abort, pause, prompts, faults.

The test bench (:func:`make_bench`) speaks the driver interfaces and keeps command logs like
the real and simulated instruments; its digitizer synthesises echoes of a point moving with
a known receptance, so the FRF the runner stores can be checked against the truth. It runs
faster than real time (``pace``).
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from pelvislab.acquisition import runner as r
from pelvislab.acquisition.protocol import Point
from pelvislab.acquisition.session import SessionReader
from pelvislab.drivers.bench import Bench, BenchConfig
from pelvislab.drivers.interfaces import InstrumentError, InstrumentTimeoutError, SegmentedRecord

pytest.importorskip("pelvislab.acquisition.tracking")
pytest.importorskip("pelvislab.acquisition.phasor")

POINTS = {
    "a": Point("a", "sacrum", (-0.15, 0.0, -0.05), (-1.0, 0.0, 0.0)),
    "b": Point("b", "innominate_left", (0.0, 0.11, 0.0), (1.0, 0.0, 0.0)),
    "c": Point("c", "innominate_right", (0.0, -0.11, 0.0), (1.0, 0.0, 0.0)),
}
POINTS_TOML = "".join(
    f"[points.{k}]\nbone = \"{p.bone}\"\nposition_m = {list(p.position_m)}\n"
    f"direction = {list(p.direction)}\n" for k, p in POINTS.items())
PROTOCOL = """
schema = "pelvislab-protocol"
schema_version = 1
name = "runner-test"
[sweep]
frequencies_hz = [60.0, 100.0, 140.0, 180.0]
drive_vpp = 0.4
settle_s = 0.05
[ultrasound]
pulses = 400
samples = 160
delay_s = 10e-6
[[setups]]
name = "s1"
excitation = "a"
transducers = { ch1 = "a", ch2 = "b" }
[[setups]]
name = "s2"
excitation = "c"
transducers = { ch1 = "b" }
""" + POINTS_TOML


def true_receptance(point: str, frequency_hz: float) -> complex:
    """A made-up 1-DOF receptance per point (m/N) the test digitizer applies."""
    fn = {"a": 120.0, "b": 150.0, "c": 90.0}[point]
    w, wn = 2 * math.pi * frequency_hz, 2 * math.pi * fn
    return 1e-6 / (1 - (w / wn) ** 2 + 2j * 0.1 * w / wn)


class Log:
    def __init__(self):
        self.command_log: list[tuple[float, str]] = []

    def _log(self, text):
        self.command_log.append((time.monotonic(), text))


class TestGenerator(Log):
    __test__ = False

    def __init__(self, name, fail_on=None, fail_after=0):
        super().__init__()
        self.identity, self.resource = f"TEST,{name}", f"TEST::{name}"
        self.enabled = False
        self.frequency_hz = 0.0
        self.amplitude_vpp = 0.0
        self.fail_on, self.fail_after, self.calls = fail_on, fail_after, 0

    def _maybe_fail(self, what):
        if what == self.fail_on:
            self.calls += 1
            if self.calls > self.fail_after:
                self._log(f"FAULT {what}")
                raise InstrumentError(f"{self.identity}: -222 data out of range ({what})")

    def configure_sine(self, frequency_hz, amplitude_vpp, offset_v=0.0):
        self.frequency_hz, self.amplitude_vpp = frequency_hz, amplitude_vpp
        self._log(f"APPL:SIN {frequency_hz},{amplitude_vpp}")

    def set_frequency(self, frequency_hz):
        self._maybe_fail("set_frequency")
        self.frequency_hz = frequency_hz
        self._log(f"FREQ {frequency_hz}")

    def set_amplitude(self, amplitude_vpp):
        self.amplitude_vpp = amplitude_vpp
        self._log(f"VOLT {amplitude_vpp}")

    def configure_pulse_burst(self, prf_hz, n_pulses, width_s, high_v, low_v=0.0):
        self._log(f"BURS {prf_hz},{n_pulses}")

    def output_on(self):
        self._maybe_fail("output_on")
        self.enabled = True
        self._log("OUTP ON")

    def output_off(self):
        self.enabled = False
        self._log("OUTP OFF")

    @property
    def output_enabled(self):
        return self.enabled

    def reference_locked(self):
        return True

    def safe_state(self):
        self.output_off()

    def close(self):
        self.safe_state()


class TestDigitizer(Log):
    __test__ = False

    def __init__(self, drive, config, pace=0.05, fail_at=None, hang_at=None, seed=0):
        super().__init__()
        self.identity, self.resource = "TEST,digitizer", "TEST::dig"
        self.drive, self.config, self.pace = drive, config, pace
        self.fail_at, self.hang_at = fail_at, hang_at
        self.n_acquired = 0
        self.rng = np.random.default_rng(seed)
        self.points = {1: "a", 2: "b"}
        self._abort = threading.Event()

    def configure_sequence(self, channels, sample_rate_hz, n_samples, n_segments, delay_s,
                           full_scale_v, offset_v=0.0):
        self.channels, self.fs, self.n_samples = list(channels), sample_rate_hz, n_samples
        self.n_segments, self.delay_s, self.full_scale_v = n_segments, delay_s, full_scale_v
        self._log(f"configure {channels} {n_segments}x{n_samples}")

    def acquire(self, timeout_s):
        self._abort.clear()
        self.n_acquired += 1
        self._log("acquire")
        if self.fail_at == self.n_acquired:
            self._log("FAULT acquire")
            raise InstrumentTimeoutError("digitizer: acquisition timed out (no trigger)")
        duration = self.n_segments / 5000.0 * self.pace
        if self.hang_at == self.n_acquired:
            duration = 30.0
        if self._abort.wait(duration):
            raise InstrumentError("digitizer: acquisition aborted")
        f = self.drive.frequency_hz
        force = self.config.drive_newton_per_volt * r.drive_voltage_phasor(
            self.drive.amplitude_vpp if self.drive.enabled else 0.0)
        t_pulse = np.arange(self.n_segments) / 5000.0
        records = {}
        for ch in self.channels:
            x = np.real(true_receptance(self.points[ch], f) * force
                        * np.exp(2j * np.pi * f * t_pulse))
            off = self.rng.uniform(-1 / self.fs, 0, self.n_segments)
            tau = 10.15e-6 - 2 * x / 1540.0
            t = self.delay_s + np.arange(self.n_samples)[None, :] / self.fs + off[:, None]
            d = t - tau[:, None]
            v = 90 * np.exp(-0.5 * (d / 0.1e-6) ** 2) * np.cos(2 * np.pi * 5e6 * d)
            v += self.rng.normal(0, 1.0, v.shape)
            records[ch] = SegmentedRecord(np.clip(np.round(v), -128, 127).astype(np.int8), off,
                                          self.fs, self.delay_s, 0.004, 0.0)
        return records

    def abort(self):
        self._abort.set()
        self._log("abort")

    def close(self):
        self.abort()


class TestPulser(Log):
    __test__ = False

    def __init__(self, i):
        super().__init__()
        self.identity, self.resource = f"TEST,pulser{i}", f"TEST::p{i}"

    def configure(self, gain_db, pulse_energy, damping_ohm, high_pass_hz, low_pass_hz):
        self._log(f"gain {gain_db}")

    def safe_state(self):
        self._log("quiet")

    def close(self):
        self.safe_state()


class TestBench(Bench):
    """A Bench whose simulated operator can move the transducers (like the sim's world)."""

    __test__ = False

    def place(self, excitation, channels, excitation_direction, speed_of_sound_m_s=None):
        self.digitizer.points = {ch: p.name for ch, p in channels.items()}
        self.digitizer.excitation = excitation


def make_bench(pace=0.05, drive_fail=None, drive_fail_after=0, fail_at=None, hang_at=None):
    config = BenchConfig(name="test bench", drive_newton_per_volt=complex(8.0, -0.5))
    drive = TestGenerator("drive", drive_fail, drive_fail_after)
    trigger = TestGenerator("trigger")
    digitizer = TestDigitizer(drive, config, pace, fail_at, hang_at)
    return TestBench(trigger=trigger, drive=drive, digitizer=digitizer,
                 pulsers=[TestPulser(1), TestPulser(2)], config=config, simulated=True)


def prepare(tmp_path, bench, auto_continue=True, text=PROTOCOL):
    proto = tmp_path / "p.toml"
    proto.write_text(text)
    return r.prepare_session(proto, tmp_path / "s.h5", bench=bench, auto_continue=auto_continue)


def off_times(generator) -> list[float]:
    return [t for t, s in generator.command_log if s == "OUTP OFF"]


# --------------------------------------------------------------------------- tests
def test_complete_run_events_and_frf(tmp_path):
    bench = make_bench()
    events = []
    with prepare(tmp_path, bench) as session:
        session.runner.subscribe(events.append)
        final = session.run()
    assert final.status == "completed" and final.n_done == final.n_steps == 8
    kinds = [type(e).__name__ for e in events]
    assert kinds[0] == "RunStarted" and kinds[-1] == "RunFinished"
    assert kinds.count("StepFinished") == 8 and kinds.count("OperatorPrompt") == 2
    assert kinds.count("Progress") == 8 and kinds.count("Quality") == 12
    assert all(e.ok for e in events if isinstance(e, r.Quality))
    progress = [e for e in events if isinstance(e, r.Progress)]
    assert progress[-1].eta_s == 0 and progress[-1].fraction == 1
    assert not bench.drive.enabled and not bench.trigger.enabled
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.status == ("completed", "")
        frf = reader.frf()
        steps = list(reader.steps())
        assert "gate_start" in steps[0].channels[0].quality
        assert any("auto-continued" in line for line in reader.log_lines())
        logs = reader.handle["runs/000/command_logs/drive/text"][()]
        assert b"OUTP OFF" in list(logs)
        # the trigger generator is configured (pulse burst) before its output goes on: in
        # its *RST state it would fire the pulsers (helper review, session 34)
        trig = [bytes(t) for t in reader.handle["runs/000/command_logs/trigger/text"][()]]
        burst = next(i for i, t in enumerate(trig) if t.startswith(b"BURS"))
        assert burst < trig.index(b"OUTP ON"), trig[:10]
    # the stored FRF is the receptance the test bench applied (ch. 8 accuracy: a few %)
    for i, f in enumerate(frf.frequency_hz):
        for o, name in enumerate(frf.outputs.name):
            for j, exc in enumerate(frf.inputs.name):
                if np.isfinite(frf.H[i, o, j]):
                    truth = true_receptance(name, f)
                    assert abs(frf.H[i, o, j] - truth) < 0.05 * abs(truth), (f, name, exc)
    assert np.isfinite(frf.H).sum() == 4 * 2 + 4


def test_abort_from_another_thread_turns_outputs_off_at_once(tmp_path):
    # real time (80 ms per acquisition), and the third acquisition would last 30 s: the
    # abort comes during it, so outputs that waited for the runner's next step (or for
    # the acquisition to end) would go off ~30 s late, far beyond the bound, which is
    # loose enough for a loaded CI machine (a bound of 0.1 s on an 80 ms acquisition
    # could not tell the two apart under load)
    bench = make_bench(pace=1.0, hang_at=3)
    with prepare(tmp_path, bench) as session:
        result = {}
        thread = threading.Thread(target=lambda: result.setdefault("f", session.run()))
        thread.start()
        deadline = time.monotonic() + 60
        while bench.digitizer.n_acquired < 3:
            assert thread.is_alive() and time.monotonic() < deadline, "no third acquisition"
            time.sleep(0.005)
        t_abort = time.monotonic()
        session.runner.abort("operator pressed STOP")
        thread.join(10)
        # before the session's close, which would abort and end the run too
        assert not thread.is_alive(), "the run did not end after the abort"
    final = result["f"]
    assert final.status == "aborted" and "STOP" in final.reason
    for gen in (bench.drive, bench.trigger):
        assert min(t for t in off_times(gen) if t >= t_abort) - t_abort < 1.0
        assert not gen.enabled
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.status[0] == "aborted"
        assert len(list(reader.steps())) >= 2


def test_pause_turns_drive_off_and_resume_continues(tmp_path):
    bench = make_bench()
    events = []
    with prepare(tmp_path, bench) as session:
        runner = session.runner

        def listener(event):
            events.append(event)
            if isinstance(event, r.StepFinished) and event.step.index == 1:
                runner.pause()
                threading.Timer(0.1, runner.resume).start()
                runner.add_note("subject coughed")

        runner.subscribe(listener)
        final = session.run()
    assert final.status == "completed"
    paused = next(e for e in events if isinstance(e, r.Paused))
    assert not any(isinstance(e, r.StepStarted) and e.t_s > paused.t_s and e.step.index == 1
                   for e in events)
    texts = [t for _, t in bench.drive.command_log]
    i_pause = max(i for i, t in enumerate(texts[:texts.index("FREQ 140.0")]) if t == "OUTP OFF")
    assert "OUTP ON" in texts[i_pause:texts.index("FREQ 140.0")]
    with SessionReader(tmp_path / "s.h5") as reader:
        assert any("NOTE subject coughed" in line for line in reader.log_lines())


def test_prompt_waits_for_confirmation_with_outputs_off(tmp_path):
    bench = make_bench()
    with prepare(tmp_path, bench, auto_continue=False) as session:
        runner = session.runner
        seen = []

        def listener(event):
            if isinstance(event, r.OperatorPrompt):
                seen.append((event.setup, bench.drive.enabled))
                threading.Timer(0.05, runner.confirm).start()

        runner.subscribe(listener)
        final = session.run()
    assert final.status == "completed"
    assert seen == [("s1", False), ("s2", False)]


def test_a_pause_asked_at_a_prompt_keeps_the_outputs_off_until_resumed(tmp_path):
    # GUI review, session 35: Pause at the transducer prompt, then confirm: both outputs
    # went ON and at once OFF again (a burst on the subject during a pause)
    bench = make_bench()
    with prepare(tmp_path, bench, auto_continue=False) as session:
        runner = session.runner
        resumed = []

        paused = []

        def listener(event):
            if isinstance(event, r.OperatorPrompt) and event.setup == "s2":
                paused.append(time.monotonic())
                runner.pause()
                runner.confirm()
            if isinstance(event, r.Paused):
                threading.Timer(0.1, lambda: (resumed.append(time.monotonic()),
                                              runner.resume())).start()
            elif isinstance(event, r.OperatorPrompt):
                threading.Timer(0.05, runner.confirm).start()

        runner.subscribe(listener)
        final = session.run()
    assert final.status == "completed" and resumed
    drive_on = [t for t, text in bench.drive.command_log if text == "OUTP ON"]
    assert len(drive_on) == 2, bench.drive.command_log  # once per setup, the 2nd after resume
    assert drive_on[1] > resumed[0]
    # the trigger also pulses for the live echoes at s1's prompt (the drive off then);
    # nothing is switched on between the pause and the resume
    trigger_on = [t for t, text in bench.trigger.command_log if text == "OUTP ON"]
    assert not [t for t in trigger_on if paused[0] <= t <= resumed[0]]
    assert trigger_on[-1] > resumed[0]


@pytest.mark.parametrize("fault", ["digitizer", "generator"])
def test_instrument_fault_outputs_off_reason_kept_data(tmp_path, fault):
    if fault == "digitizer":
        bench = make_bench(fail_at=3)
    else:
        bench = make_bench(drive_fail="set_frequency", drive_fail_after=2)
    # what the outputs were when the listeners (file writer, GUI) heard of the fault: off
    # already, whatever the machine's load (a time bound alone could not tell "off first"
    # from "off after the listeners")
    on_at_fault = []
    with prepare(tmp_path, bench) as session:
        session.runner.subscribe(lambda e: on_at_fault.append(
            (bench.drive.enabled, bench.trigger.enabled)) if isinstance(e, r.Fault) else None)
        final = session.run()
    assert final.status == "failed"
    assert on_at_fault == [(False, False)]
    assert ("timed out" in final.reason) if fault == "digitizer" else ("-222" in final.reason)
    assert "\n" not in final.reason
    log = bench.digitizer.command_log if fault == "digitizer" else bench.drive.command_log
    t_fault = next(t for t, s in log if s.startswith("FAULT"))
    for gen in (bench.drive, bench.trigger):
        assert not gen.enabled
        assert min(t for t in off_times(gen) if t >= t_fault) - t_fault < 1.0
    with SessionReader(tmp_path / "s.h5") as reader:
        assert len(list(reader.steps())) == 2
        status, reason = reader.status
        assert status == "failed" and reason == final.reason


def test_resume_measures_only_what_is_missing(tmp_path):
    bench = make_bench(fail_at=4)
    with prepare(tmp_path, bench) as session:
        assert session.run().status == "failed"
    bench2 = make_bench()
    proto = tmp_path / "p.toml"
    with SessionReader(tmp_path / "s.h5") as reader:
        subject = reader.attrs["subject_id"]
    # another subject's ID is refused before the bench is touched (two subjects' steps
    # would end up in one FRF)
    with pytest.raises(ValueError, match=f"session of subject '{subject}', not 'X99'"):
        r.prepare_session(proto, tmp_path / "s.h5", bench=bench2, resume=True,
                          subject_id="X99")
    assert not bench2.drive.command_log
    with r.prepare_session(proto, tmp_path / "s.h5", bench=bench2, resume=True,
                           subject_id=subject) as session:
        assert len(session.runner.protocol.steps()) == 8
        final = session.run()
    assert final.status == "completed" and final.n_done == 8
    assert bench2.digitizer.n_acquired == 5
    with SessionReader(tmp_path / "s.h5") as reader:
        keys = [s.key for s in reader.steps()]
        assert len(keys) == len(set(keys)) == 8
        assert np.isfinite(reader.frf().H).sum() == 12


def test_listener_failure_is_not_a_fault_unless_critical(tmp_path):
    bench = make_bench()
    with prepare(tmp_path, bench) as session:
        session.runner.subscribe(lambda e: 1 / 0)
        assert session.run().status == "completed"
    bench = make_bench()
    with prepare(tmp_path / "x" if (tmp_path / "x").mkdir() is None else tmp_path,
                 bench) as session:
        def disk_full(event):
            if isinstance(event, r.StepFinished) and event.step.index == 2:
                raise OSError(28, "No space left on device")
        session.runner.subscribe(disk_full, critical=True)
        final = session.run()
    assert final.status == "failed" and "No space left" in final.reason
    assert not bench.drive.enabled


def test_a_failing_critical_listener_does_not_keep_the_end_from_the_others(tmp_path):
    """A session writer whose writes all fail after one refused write (its file left
    without writing again) raises on the Fault and RunFinished too: the listeners after it
    (the GUI's) never heard that the run ended and the window showed "RUNNING — OUTPUTS ON"
    with the outputs off (session 51)."""
    bench = make_bench()
    heard = []
    with prepare(tmp_path, bench) as session:
        failed = []

        def writer(event):
            if failed or (isinstance(event, r.StepFinished) and event.step.index == 2):
                failed.append(event)
                raise OSError(5, "Input/output error")
        session.runner.subscribe(writer, critical=True)
        session.runner.subscribe(heard.append)
        final = session.run()
    assert final.status == "failed" and "Input/output error" in final.reason
    assert len(failed) > 2  # it refused the Fault and the run's end as well
    faults = [e for e in heard if isinstance(e, r.Fault)]
    ends = [e for e in heard if isinstance(e, r.RunFinished)]
    assert len(faults) == 1 and "Input/output error" in faults[0].reason
    assert len(ends) == 1 and ends[0].status == "failed" and not ends[0].unsafe
    assert not bench.drive.enabled


def test_reprocess_from_raw_echoes(tmp_path):
    bench = make_bench()
    with prepare(tmp_path, bench) as session:
        session.run()
    out = tmp_path / "s2.h5"
    from pelvislab.acquisition.tracking import TrackingOptions

    options = TrackingOptions(estimator="parabolic")
    n, problems = r.reprocess_session(tmp_path / "s.h5", out, options)
    assert n == 8 and not problems
    with SessionReader(tmp_path / "s.h5") as a, SessionReader(out) as b:
        fa, fb = a.frf(), b.frf()
        assert np.isfinite(fb.H).sum() == np.isfinite(fa.H).sum()
        m = np.isfinite(fa.H)
        np.testing.assert_allclose(fb.H[m], fa.H[m], rtol=0.05)
        assert "parabolic" in b.log_lines()[-1]
        sa, sb = next(a.steps()), next(b.steps())
        np.testing.assert_array_equal(sa.channels[0].codes, sb.channels[0].codes)


def test_close_while_running_aborts_then_closes(tmp_path):
    bench = make_bench(pace=1.0)
    session = prepare(tmp_path, bench)
    thread = threading.Thread(target=session.run)
    thread.start()
    while bench.digitizer.n_acquired < 2:
        time.sleep(0.005)
    session.close()
    thread.join(5)
    assert session.final.status == "aborted" and not bench.drive.enabled
    session.close()  # idempotent
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.status == ("aborted", "session closed while running")


def test_reprocess_with_unusable_options_fails_and_writes_nothing(tmp_path):
    bench = make_bench()
    with prepare(tmp_path, bench) as session:
        session.run()
    from pelvislab.acquisition.tracking import TrackingOptions

    out = tmp_path / "bad.h5"
    # a gate past the end of the records: only the first step's records can tell
    with pytest.raises(ValueError, match=r"gate \(0, 10000000\) for ch1 \(step 0\): .*"
                                         r"leave the lag range"):
        r.reprocess_session(tmp_path / "s.h5", out, TrackingOptions(gate=(0, 10**7)))
    assert not out.exists()
    # what the options alone show is refused before any work (session 34: an unknown
    # estimator was found at the first step, in a message quoting every option)
    with pytest.raises(ValueError, match="tracking option estimator = 'nonsense'"):
        TrackingOptions(estimator="nonsense")
    with pytest.raises(ValueError, match="tracking option gate"):
        TrackingOptions(gate=(400, 100))
    with pytest.raises(ValueError, match="tracking option band_hz"):
        TrackingOptions(band_hz="abc")  # what --tracking band_hz=abc passed on


def test_reprocess_refuses_nonsense_and_publishes_only_a_complete_file(tmp_path):
    # before: --min-correlation 2 wrote a session whose /frf was all NaN ("reprocessed 14
    # steps"), --speed-of-sound 0 was silently ignored, and a killed reprocess left a
    # damaged file at --out that blocked the next try
    from pelvislab.acquisition.tracking import TrackingOptions

    bench = make_bench()
    with prepare(tmp_path, bench) as session:
        session.run()
    src, out = tmp_path / "s.h5", tmp_path / "r.h5"
    with pytest.raises(ValueError, match="min_correlation = 2"):
        TrackingOptions(min_correlation=2.0)
    with pytest.raises(ValueError, match="block_size"):
        TrackingOptions(block_size=0)
    for c in (0.0, float("nan"), 1e9):
        with pytest.raises(ValueError, match="speed of sound"):
            r.reprocess_session(src, out, None, c)
    with pytest.raises(ValueError, match="no step kept an FRF line"):
        r.reprocess_session(src, out, TrackingOptions(min_correlation=1.0))
    assert not out.exists()
    seen = []
    n, _ = r.reprocess_session(src, out, None, None,
                               lambda done, total: seen.append(out.exists()))
    assert n == 8 and seen and not any(seen)  # the name appears only when complete
    assert out.is_file() and not [f for f in tmp_path.iterdir() if f.suffix == ".partial"]


def test_repeats_are_merged_by_inverse_variance_and_resumable(tmp_path):
    from pelvislab.acquisition.session import combine_lines

    text = PROTOCOL.replace("drive_vpp = 0.4", "drive_vpp = 0.4\nrepeats = 2")
    bench = make_bench(fail_at=6)
    with prepare(tmp_path, bench, text=text) as session:
        assert len(session.protocol.steps()) == 16
        assert session.run().status == "failed"
    with r.prepare_session(tmp_path / "p.toml", tmp_path / "s.h5", bench=make_bench(),
                           resume=True) as session:
        assert session.run().status == "completed"
    with SessionReader(tmp_path / "s.h5") as reader:
        steps = list(reader.steps())
        frf = reader.frf()
    assert sorted(s.key for s in steps) == sorted(p.key for p in session.protocol.steps())
    first = [s for s in steps if s.setup == "s1" and s.frequency_hz == 60.0]
    assert sorted(int(s.extra["repeat"]) for s in first) == [0, 1]
    values = [(s.channels[0].phasor_m / s.force_phasor_n,
               s.channels[0].phasor_std_m / abs(s.force_phasor_n)) for s in first]
    h, h_std = combine_lines(values)
    i, o, j = 0, frf.outputs.index("a"), frf.inputs.index("a")
    assert frf.H[i, o, j] == pytest.approx(h) and frf.H_std[i, o, j] == pytest.approx(h_std)
    assert h_std < min(v[1] for v in values)


def test_console_progress_bar_on_a_terminal(tmp_path):
    import io

    from pelvislab.app.commands.run import ConsoleProgress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    stream = Tty()
    bench = make_bench()
    with prepare(tmp_path, bench) as session:
        session.runner.subscribe(ConsoleProgress(session.runner, stream))
        session.run()
    text = stream.getvalue()
    assert "\r[" in text and "8/8 steps" in text and "ETA" in text
    assert "prompt (auto-continue)" in text


def test_a_reprocessed_session_is_judged_again_and_not_resumed(tmp_path):
    # replay review, session 36: reprocess copied each step's quality_ok as recorded, and
    # its copy of /runs ("aborted") let `run --resume` append steps tracked with the
    # recording's options to a file re-tracked with others
    import h5py

    from pelvislab.app.commands._common import incomplete_session_warning

    bench = make_bench()
    with prepare(tmp_path, bench) as session:
        def stop_after_two(event):
            if isinstance(event, r.StepFinished) and event.step.index == 1:
                session.runner.abort("stopped for the test")
        session.runner.subscribe(stop_after_two)
        assert session.run().status == "aborted"
    src, out = tmp_path / "s.h5", tmp_path / "r.h5"
    # the protocol measures 3 pairs (a and b driven at a, b at c) in 2 x 2 /frf cells
    assert "(2 of the 3 planned FRFs hold data; --resume the run" in \
        incomplete_session_warning(src)
    with h5py.File(src, "r+") as f:
        for name in f["steps"]:
            f["steps"][name].attrs["quality_ok"] = False  # as if judged bad when recorded
    assert r.reprocess_session(src, out)[0] == 2
    with h5py.File(out, "r") as f:
        assert [bool(f["steps"][n].attrs["quality_ok"]) for n in f["steps"]] == [True, True]
    assert f"resume its source session {src} and reprocess that" in \
        incomplete_session_warning(out)
    with pytest.raises(ValueError, match=f"was reprocessed from {src}; resume that session"):
        r.prepare_session(tmp_path / "p.toml", out, bench=make_bench(), resume=True)
