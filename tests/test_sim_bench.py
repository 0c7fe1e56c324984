"""The simulated bench end to end: interfaces, physics through the instruments, faults."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pelvislab.drivers.bench import BenchConfig, open_bench
from pelvislab.drivers.interfaces import (
    Digitizer,
    Generator,
    InstrumentConnectionError,
    InstrumentError,
    InstrumentTimeoutError,
    LimitError,
    PulserReceiver,
)
from pelvislab.sim_instruments.bench import open_simulated_bench
from pelvislab.sim_instruments.effects import SpeedOfSoundError, StaticClutter, SubjectDrift
from pelvislab.sim_instruments.faults import (
    DigitizerTimeout,
    InstrumentTimeout,
    LostConnection,
    PulserSilent,
    ScpiError,
)
from pelvislab.tests.sim_tracking_helper import phasor, track

PRF = 5000.0


def _arm(bench, n=400, frequency_hz=80.0, vpp=1.0, channels=(1, 2)):
    for ch in channels:
        bench.pulsers[ch - 1].configure(40.0, "low", 50.0, None, None)
    bench.trigger.configure_pulse_burst(PRF, n, 1e-6, 5.0)
    bench.digitizer.configure_sequence(list(channels), 500e6, 500, n, 10e-6, 1.0)
    bench.drive.configure_sine(frequency_hz, vpp)
    bench.drive.output_on()
    bench.trigger.output_on()


@pytest.fixture
def bench():
    b = open_simulated_bench(generators="python", seed=1)
    yield b
    b.close()


def test_open_bench_none_is_the_simulated_bench_with_the_real_driver_over_pyvisa_sim():
    with open_bench(None) as b:
        assert b.simulated
        assert isinstance(b.drive, Generator) and isinstance(b.trigger, Generator)
        assert isinstance(b.digitizer, Digitizer)
        assert all(isinstance(p, PulserReceiver) for p in b.pulsers)
        assert "33220A" in b.drive.identity
        _arm(b, n=100)
        assert b.drive.output_enabled  # asked through pyvisa-sim (OUTP?)
        records = b.digitizer.acquire(2.0)
        assert set(records) == {1, 2}
        assert records[1].codes.shape == (100, 500) and records[1].codes.dtype == np.int8
    # leaving the block: every output off, seen in the instruments' own logs
    for gen, state in ((b.drive, b.world.drive), (b.trigger, b.world.trigger)):
        assert not state.output
        last_outp = [text for _, text in gen.command_log if text.startswith("OUTP ")][-1]
        assert last_outp == "OUTP OFF"


def test_records_carry_the_model_displacement_with_the_sync_phase(bench):
    _arm(bench, n=2000, frequency_hz=80.0, vpp=1.0)
    records = bench.digitizer.acquire(5.0)
    truth = bench.world.truth[-1]
    # 33220A SYNC edge = sine phase 0 at the first pulse: V = -i Vpp/2, F = (N/V) V
    assert truth.voltage_phasor_v == pytest.approx(-0.5j, abs=1e-12)
    assert truth.force_phasor_n == pytest.approx(complex(bench.config.drive_newton_per_volt)
                                                 * -0.5j)
    H = bench.world.frf(80.0)
    for ch in (1, 2):
        assert truth.displacement_phasor_m[ch] == pytest.approx(H[ch] * truth.force_phasor_n)
        U = phasor(track(records[ch], 1540.0), PRF, 80.0)
        T = truth.measured_phasor_m[ch]
        assert abs(U / T - 1) < 0.02, ch  # amplitude and phase (0.02 rad) at 30 dB SNR


def test_drive_off_means_no_motion_and_trigger_off_means_no_records(bench):
    _arm(bench, n=400)
    bench.drive.output_off()
    records = bench.digitizer.acquire(2.0)
    assert bench.world.truth[-1].displacement_phasor_m[1] == 0
    u = track(records[1], 1540.0)
    # per-echo jitter ~0.1 um at 30 dB SNR; the phasor of 400 echoes averages it down
    assert abs(phasor(u, PRF, 80.0)) < 2e-8
    bench.trigger.output_off()
    with pytest.raises(InstrumentTimeoutError, match="output is off"):
        bench.digitizer.acquire(2.0)


def test_a_burst_shorter_than_the_sequence_times_out(bench):
    _arm(bench, n=400)
    bench.trigger.configure_pulse_burst(PRF, 100, 1e-6, 5.0)
    with pytest.raises(InstrumentTimeoutError, match="100 pulses"):
        bench.digitizer.acquire(2.0)


def test_unconfigured_pulser_gives_noise_only(bench):
    _arm(bench, n=50, channels=(1,))
    bench.digitizer.configure_sequence([1, 2], 500e6, 500, 50, 10e-6, 1.0)
    records = bench.digitizer.acquire(2.0)
    assert np.abs(records[1].codes).max() > 50  # a live echo
    assert np.abs(records[2].codes).max() < 20  # pulser 2 never fired: noise


def test_seeded_and_reproducible():
    def run(seed):
        # drift (a random walk) and the SYNC wait depend on the world's clock: fast pacing
        # keeps it virtual, so wall-clock jitter cannot change the records
        with open_simulated_bench(generators="python", seed=seed,
                                  effects=[SubjectDrift(seed=seed)]) as b:
            _arm(b, n=200)
            b.digitizer.acquire(2.0)
            time.sleep(0.01)
            b.drive.set_frequency(91.0)
            return b.digitizer.acquire(2.0)[1].codes

    a, b, c = run(5), run(5), run(6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_drive_limit_is_enforced_before_sending(bench):
    n_before = len(bench.drive.command_log)
    with pytest.raises(LimitError):
        bench.drive.configure_sine(80.0, bench.config.max_drive_vpp * 1.5)
    assert len(bench.drive.command_log) == n_before


def test_unknown_option_is_refused():
    with pytest.raises(TypeError, match="unknown option"):
        open_simulated_bench(sed=3)


def test_config_calibration_and_speed_of_sound_are_used():
    cfg = BenchConfig(drive_newton_per_volt=complex(4.0, -1.0), max_drive_vpp=3.0,
                      channel_speed_of_sound_m_s={2: 1600.0})
    with open_simulated_bench(cfg, generators="python") as b:
        _arm(b, n=200, vpp=2.5)
        b.digitizer.acquire(2.0)
        t = b.world.truth[-1]
        assert t.force_phasor_n == pytest.approx(complex(4.0, -1.0) * -1.25j)


def test_simulated_operator_moves_the_transducers(bench):
    _arm(bench, n=100)
    before = bench.world.frf(80.0)
    bench.world.place(channels={1: "SIPS_L_x", 2: "sacrum_x"})
    after = bench.world.frf(80.0)
    assert after[2] == pytest.approx(before[1])
    assert after[1] != pytest.approx(before[1])


def test_realtime_pacing_waits_like_the_real_bench():
    with open_simulated_bench(generators="python", pacing="realtime") as b:
        _arm(b, n=500)  # 0.1 s of pulses
        t0 = time.perf_counter()
        b.digitizer.acquire(2.0)
        assert time.perf_counter() - t0 >= 0.1
    with open_simulated_bench(generators="python") as b:
        _arm(b, n=500)
        clock0 = b.world.clock.now()
        b.digitizer.acquire(2.0)
        assert b.world.clock.now() - clock0 >= 0.1  # fast pacing: time passes virtually


# --------------------------------------------------------------------------- effects
def test_speed_of_sound_error_scales_the_tracked_displacement():
    with open_simulated_bench(generators="python", effects=[SpeedOfSoundError(0.05)]) as b:
        _arm(b, n=2000)
        # the echo comes back 0.5 us earlier (10.14 us): move the record to keep it inside
        b.digitizer.configure_sequence([1, 2], 500e6, 500, 2000, 9.6e-6, 1.0)
        records = b.digitizer.acquire(5.0)
        t = b.world.truth[-1]
        assert t.measured_phasor_m[1] == pytest.approx(t.displacement_phasor_m[1] / 1.05)
        U = phasor(track(records[1], 1540.0), PRF, 80.0)
        assert abs(U / t.measured_phasor_m[1] - 1) < 0.02


def test_static_clutter_adds_a_still_echo():
    clutter = StaticClutter(depth_m=(8.0e-3,), level_db=(-6.0,), channels=(1,))
    with open_simulated_bench(generators="python", effects=[clutter], seed=2) as b0:
        pass
    with open_simulated_bench(generators="python", seed=2) as plain, \
            open_simulated_bench(generators="python", effects=[clutter], seed=2) as b:
        for x in (plain, b):
            _arm(x, n=50)
            x.drive.output_off()
        d = b.digitizer.acquire(2.0)[1].volts() - plain.digitizer.acquire(2.0)[1].volts()
    assert b0.world.echo_effects == [clutter]
    assert np.abs(d).max() > 0.05
    # the clutter does not move: the difference is the same in every segment up to the noise
    # and sub-sample trigger offsets
    assert np.std(d, axis=0).max() < 0.1 * np.abs(d).max() + 0.03


def test_subject_drift_shows_in_the_truth_and_in_the_records():
    drift = SubjectDrift(rate_m_per_s=200e-6, random_walk_m_per_sqrt_s=0.0)
    with open_simulated_bench(generators="python", effects=[drift]) as b:
        _arm(b, n=2000)
        b.drive.output_off()
        records = b.digitizer.acquire(5.0)
        t = b.world.truth[-1]
        span = t.drift_m[1][-1] - t.drift_m[1][0]
        assert span == pytest.approx(200e-6 * 1999 / PRF)
        u = track(records[1], 1540.0)
        # deeper = away from the transducer = negative displacement
        assert u[-100:].mean() - u[:100].mean() == pytest.approx(-span * 0.95, rel=0.1)


# --------------------------------------------------------------------------- faults
def test_scpi_error_in_the_queue_is_raised_by_the_real_driver():
    with open_simulated_bench(generators="python") as b:
        n = b.drive.transport.n_commands
        b.world.faults.faults.append(ScpiError("drive", at_command=n + 1, code=-222,
                                               message="Data out of range"))
        with pytest.raises(InstrumentError, match="Data out of range"):
            b.drive.configure_sine(80.0, 0.5)
        assert not b.world.drive.output  # the driver put the output off


def test_generator_timeout_and_lost_connection_mid_sweep():
    with open_simulated_bench(generators="python") as b:
        _arm(b, n=100)
        n = b.drive.transport.n_commands
        b.world.faults.faults.append(InstrumentTimeout("drive", at_command=n))
        with pytest.raises(InstrumentTimeoutError):
            b.drive.set_frequency(90.0)
        b.world.faults.faults.append(LostConnection("trigger",
                                                    at_command=b.trigger.transport.n_commands))
        with pytest.raises(InstrumentConnectionError):
            b.trigger.configure_pulse_burst(PRF, 100, 1e-6, 5.0)
        b.safe_state()  # never raises, even with a lost instrument
        assert b.world.trigger.output  # ... but it could not switch that output off
        assert b.trigger.safe_state_errors
        assert not b.world.drive.output


def test_digitizer_timeout_and_lost_connection():
    faults = [DigitizerTimeout(at_acquisition=1), LostConnection("digitizer", at_acquisition=3)]
    with open_simulated_bench(generators="python", faults=faults) as b:
        _arm(b, n=100)
        b.digitizer.acquire(2.0)
        with pytest.raises(InstrumentTimeoutError, match="injected"):
            b.digitizer.acquire(2.0)
        b.digitizer.acquire(2.0)
        with pytest.raises(InstrumentConnectionError):
            b.digitizer.acquire(2.0)
        with pytest.raises(InstrumentConnectionError):
            b.digitizer.configure_sequence([1], 500e6, 500, 100, 10e-6, 1.0)
        b.digitizer.abort()  # never raises


def test_a_pulser_that_does_not_answer():
    with open_simulated_bench(generators="python", faults=[PulserSilent(channel=2)]) as b:
        b.pulsers[0].configure(40.0, "low", 50.0, None, None)
        with pytest.raises(InstrumentTimeoutError, match="no answer"):
            b.pulsers[1].configure(40.0, "low", 50.0, None, None)
        b.pulsers[1].safe_state()  # never raises


def test_fault_names_are_checked():
    with pytest.raises(ValueError, match="unknown"):
        open_simulated_bench(faults=[InstrumentTimeout("shaker")])


def test_misconfigured_digitizer_is_refused(bench):
    with pytest.raises(LimitError):
        bench.digitizer.configure_sequence([3], 500e6, 500, 10, 10e-6, 1.0)
    with pytest.raises(LimitError):
        bench.digitizer.configure_sequence([1], 1e9, 500, 10, 10e-6, 1.0)
    with pytest.raises(LimitError):
        bench.digitizer.configure_sequence([1], 500e6, 500, 10, 10e-6, 50.0)


def test_layout_comes_from_the_catalogue_and_the_shaker_pushes_into_the_bone(bench):
    from pelvislab.acquisition.protocol import load_landmarks
    from pelvislab.sim_instruments.layout import FALLBACK_LANDMARKS

    catalogue = load_landmarks()
    assert set(FALLBACK_LANDMARKS) <= set(catalogue)
    world = bench.world
    assert world.excitation.position_m == pytest.approx(catalogue["SIAS_R_x"].position_m)
    _, outputs, inputs = world._points()
    assert inputs.direction[0] == pytest.approx(-np.asarray(catalogue["SIAS_R_x"].direction))
    assert outputs.direction[0] == pytest.approx(catalogue["sacrum_x"].direction)
    # the runner's simulated operator passes protocol points and the force direction
    point = catalogue["SIPS_L_x"]
    world.place(excitation=point, channels={1: catalogue["sacrum_x"]},
                excitation_direction=(0.0, 0.0, 1.0))
    _, outputs, inputs = world._points()
    assert inputs.bone == ("innominate_left",) and inputs.direction[0] == pytest.approx([0, 0, 1])
    assert outputs.name == ("sacrum_x",)


def test_real_acqiris_driver_over_the_simulated_library_gives_the_same_records():
    records = {}
    for kind in ("python", "acqiris"):
        with open_simulated_bench(generators="python", digitizer=kind, seed=4) as b:
            _arm(b, n=300)
            records[kind] = b.digitizer.acquire(2.0)
        log = [text for _, text in b.digitizer.command_log]
    assert "AcqrsD1_readData" in log and "AcqrsD1_close" in log  # the real driver's log
    for ch in (1, 2):
        a, c = records["python"][ch], records["acqiris"][ch]
        assert np.array_equal(a.codes, c.codes)
        assert np.array_equal(a.trigger_offset_s, c.trigger_offset_s)
        assert (a.volts_per_count, a.delay_s) == (c.volts_per_count, c.delay_s)


def test_real_acqiris_driver_timeout_and_lost_connection():
    faults = [LostConnection("digitizer", at_acquisition=2)]
    with open_simulated_bench(generators="python", digitizer="acqiris", faults=faults) as b:
        _arm(b, n=100)
        b.trigger.output_off()
        t0 = time.perf_counter()
        with pytest.raises(InstrumentTimeoutError, match="not finished within 0.2"):
            b.digitizer.acquire(0.2)
        assert time.perf_counter() - t0 >= 0.2  # the driver's wall-clock timeout
        b.trigger.output_on()
        b.digitizer.acquire(2.0)
        with pytest.raises(InstrumentConnectionError):
            b.digitizer.acquire(2.0)


def test_real_pulser_driver_over_the_simulated_serial_port():
    records = {}
    for kind in ("python", "panametrics"):
        with open_simulated_bench(generators="python", pulsers=kind, seed=9) as b:
            _arm(b, n=100)
            records[kind] = b.digitizer.acquire(2.0)[1].codes
            if kind == "panametrics":
                sent = [text for _, text in b.pulsers[0].command_log]
                assert {"GAIN 40", "TRIG EXT", "VOLT 100"} <= set(sent)
                with pytest.raises(LimitError):
                    b.pulsers[0].configure(40.0, "huge", 50.0, None, None)
    assert np.array_equal(records["python"], records["panametrics"])


def test_pulser_faults_with_the_real_driver():
    with pytest.raises(InstrumentTimeoutError, match="no answer"):
        open_simulated_bench(generators="python", faults=[PulserSilent(1, during_open=True)])
    faults = [LostConnection("pulser2", at_call=0)]
    with open_simulated_bench(generators="python", faults=faults) as b:
        b.pulsers[0].configure(40.0, "low", 50.0, None, None)
        with pytest.raises(InstrumentConnectionError):
            b.pulsers[1].configure(40.0, "low", 50.0, None, None)
        b.safe_state()  # never raises
        assert b.pulsers[1].safe_state_errors


def test_a_simulated_bench_file_supplies_calibration_and_limits(tmp_path):
    path = tmp_path / "sim.toml"
    path.write_text('[bench]\nname = "sim"\nsimulated = true\n[limits]\nmax_drive_vpp = 0.5\n'
                    '[calibration]\ndrive_newton_per_volt = "2-1j"\n', encoding="utf-8")
    with open_bench(path) as b:
        assert b.simulated and b.config.max_drive_vpp == 0.5
        with pytest.raises(LimitError):
            b.drive.configure_sine(80.0, 0.6)
        _arm(b, n=100, vpp=0.4)
        b.digitizer.acquire(2.0)
        assert b.world.truth[-1].force_phasor_n == pytest.approx((2 - 1j) * -0.2j)


def test_validation_phantoms_of_chapter_8(bench):
    from pelvislab.sim_instruments.layout import Landmark
    from pelvislab.sim_instruments.world import Phantom

    a = Landmark("body_a", "", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    b = Landmark("body_b", "", (0.0, 0.0, 0.02), (0.0, 0.0, 1.0))
    bench.world.place(excitation=a, channels={1: a, 2: b}, excitation_direction=(0, 0, 1))
    _arm(bench, n=2000, frequency_hz=200.0, vpp=0.2)
    records = bench.digitizer.acquire(5.0)
    # the piezo face moves 10 um/V in phase with the drive voltage (-i Vpp/2 at pulse 0)
    truth = bench.world.truth[-1]
    assert truth.displacement_phasor_m[1] == pytest.approx(1e-5 * -0.1j)
    ua = phasor(track(records[1], 1480.0), PRF, 200.0)  # water/gel: the protocols say 1480
    ub = phasor(track(records[2], 1480.0), PRF, 200.0)
    assert ua == pytest.approx(1e-5 * -0.1j, rel=0.02)
    T = Phantom().transmissibility(200.0)
    assert np.degrees(np.angle(ub / ua)) == pytest.approx(np.degrees(np.angle(T)), abs=2.0)
    assert np.degrees(np.angle(T)) == pytest.approx(-80.9, abs=5.0)  # table 8.1 at 200 Hz


def test_no_echo_warning_names_only_points_off_the_pelvis_while_the_shaker_is_on_it(tmp_path):
    """The run warned that the validation protocols' phantom faces "give no echo" while
    every step measured the phantom at ~30 dB: the simulated bench drives the ch. 8.3
    phantom wherever the excitation is on no bone. Only a point on no bone looked at while
    the shaker is on the pelvis is silent."""
    from pathlib import Path

    from pelvislab.acquisition.runner import prepare_session

    shipped = Path(__file__).resolve().parents[1] / "protocols"
    with prepare_session(shipped / "validation_amplitude.toml", tmp_path / "v.h5",
                         bench=open_simulated_bench(generators="python")) as s:
        assert s.runner._silent_on_simulated_bench() == []
    text = (shipped / "demo.toml").read_text()
    bed = ('[points.bed_frame]\nbone = ""\nposition_m = [0.0, 0.0, -0.2]\n'
           'direction = [0.0, 0.0, 1.0]\n\n[[setups]]\nname = "bed"\nexcitation = "SIAS_R_x"\n'
           'transducers = { ch1 = "bed_frame", ch2 = "sacrum_x" }\n\n')
    protocol = tmp_path / "bed.toml"
    protocol.write_text(text.replace("[[setups]]", bed + "[[setups]]", 1))
    with prepare_session(protocol, tmp_path / "b.h5",
                         bench=open_simulated_bench(generators="python")) as s:
        assert s.runner._silent_on_simulated_bench() == ["bed_frame"]
