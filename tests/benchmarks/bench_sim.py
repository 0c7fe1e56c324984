"""Simulated bench: step synthesis speed, sweep speed vs the real bench, echo statistics."""

from __future__ import annotations

import math
import time

import numpy as np

from pelvislab.tests.benchmarks.harness import Result, best_time_s

FS = 500e6
PRF = 5000.0
N_PULSES = 2000
N_SAMPLES = 500
DELAY_S = 10e-6


def _naive_step(rng: np.random.Generator) -> np.ndarray:
    """Baseline: the obvious time-domain synthesis (analytic pulse per echo, float64 noise)."""
    from pelvislab.sim_instruments.echo import Acoustics, pulse_sigma_s

    a = Acoustics()
    sigma = pulse_sigma_s(a.center_frequency_hz, a.fractional_bandwidth)
    t = DELAY_S + np.arange(N_SAMPLES) / FS
    out = []
    for _ch in (1, 2):
        u = 1e-6 * np.sin(2 * np.pi * 80 * np.arange(N_PULSES) / PRF)
        offsets = -rng.uniform(0, 1 / FS, N_PULSES)
        tau = 2 * (a.bone_depth_m - u) / a.speed_of_sound_m_s
        x = t[None, :] + offsets[:, None] - tau[:, None]
        v = 0.3 * np.exp(-x**2 / (2 * sigma**2)) * np.cos(2 * np.pi * 5e6 * x)
        v += 0.01 * rng.standard_normal(v.shape)
        out.append(np.clip(np.rint(v * 256), -128, 127).astype(np.int8))
    return np.array(out)


def _armed(vpp: float = 1.0, **options: object):
    from pelvislab.sim_instruments.bench import open_simulated_bench

    b = open_simulated_bench(**options)
    for p in b.pulsers:
        p.configure(40.0, "low", 50.0, None, None)
    b.trigger.configure_pulse_burst(PRF, N_PULSES, 1e-6, 5.0)
    b.digitizer.configure_sequence([1, 2], FS, N_SAMPLES, N_PULSES, DELAY_S, 1.0)
    b.drive.configure_sine(80.0, vpp)
    b.drive.output_on()
    b.trigger.output_on()
    return b


def _step_results() -> list[Result]:
    from pelvislab.sim_instruments.echo import Acoustics, Receiver, synthesize_channel

    rng = np.random.default_rng(0)
    baseline = best_time_s(lambda: _naive_step(rng), repeat=3)
    u = 1e-6 * np.sin(2 * np.pi * 80 * np.arange(N_PULSES) / PRF)
    offsets = -rng.uniform(0, 1 / FS, N_PULSES)

    def physics() -> None:
        for ch in (1, 2):
            synthesize_channel(Acoustics(), Receiver(), u, offsets, sample_rate_hz=FS,
                               n_samples=N_SAMPLES, delay_s=DELAY_S, full_scale_v=1.0, rng=rng,
                               speckle_seed=ch)

    physics()
    t_physics = best_time_s(physics, repeat=15)
    bench = _armed(generators="python")
    try:
        bench.digitizer.acquire(5.0)
        t_acquire = best_time_s(lambda: bench.digitizer.acquire(5.0), repeat=15)
    finally:
        bench.close()
    return [
        Result("one step 2 ch x 2000 x 500: echo synthesis (echo.py)", t_physics * 1e3, "ms",
               baseline=baseline * 1e3, baseline_name="naive time-domain",
               target="<= 50 ms"),
        Result("one step through the instruments (digitizer.acquire)", t_acquire * 1e3, "ms",
               baseline=baseline * 1e3, baseline_name="naive time-domain",
               target="<= 50 ms"),
    ]


def _sweep_results() -> list[Result]:
    """120 steps (5-302.5 Hz, 2.5 Hz) on the pyvisa-sim bench, tracked by the product."""
    from pelvislab.acquisition.phasor import estimate_phasor
    from pelvislab.acquisition.tracking import track_echoes

    freqs = 5.0 + 2.5 * np.arange(120)
    settle_s = 0.05
    real_s = sum(max(settle_s, 3.0 / f) + N_PULSES / PRF for f in freqs)
    # 0.2 Vpp = 0.1 N: 75 um at 5 Hz (free-free mass line), ~0.1 um at 300 Hz
    bench = _armed(vpp=0.2, generators="pyvisa-sim", seed=3)
    errors = []
    failed = 0
    t_sim = 0.0
    t_track = 0.0
    cpu_sim = 0.0
    cpu_track = 0.0
    try:
        t0 = time.perf_counter()
        for f in freqs:
            t1 = time.perf_counter()
            c1 = time.process_time()
            bench.drive.set_frequency(float(f))
            records = bench.digitizer.acquire(5.0)
            t2 = time.perf_counter()
            c2 = time.process_time()
            t_sim += t2 - t1
            cpu_sim += c2 - c1
            truth = bench.world.truth[-1]
            for ch, rec in records.items():
                res = track_echoes(rec.codes, rec.trigger_offset_s, rec.sample_rate_hz, 1540.0,
                                   rec.volts_per_count)
                t_track += time.perf_counter() - t2
                cpu_track += time.process_time() - c2
                t2 = time.perf_counter()
                c2 = time.process_time()
                t = np.arange(N_PULSES) / PRF
                try:
                    p = estimate_phasor(res.displacement_m, t, float(f))
                except ValueError:
                    failed += 1
                    continue
                true = truth.measured_phasor_m[ch]
                errors.append(abs(p.value / true - 1))
        wall = time.perf_counter() - t0
    finally:
        bench.close()
    errors = np.array(errors)
    return [
        Result("120-step sweep simulated + tracked + phasors (wall)", wall, "s",
               baseline=real_s, baseline_name="real bench (settle + 2000 pulses)",
               target=">= 10x faster than the real bench"),
        Result("  of which simulation (set_frequency + acquire, pyvisa-sim)", t_sim, "s",
               baseline=real_s, baseline_name="real bench", target="information"),
        Result("  of which product tracking (track_echoes, 240 records)", t_track, "s",
               baseline=real_s, baseline_name="real bench", target="information"),
        Result("  CPU time of the simulation part (less sensitive to machine load)", cpu_sim,
               "s", baseline=real_s, baseline_name="real bench", target="information"),
        Result("  CPU time of the tracking part", cpu_track, "s", baseline=real_s,
               baseline_name="real bench", target="information"),
        Result("sweep phasor error |U/U_true - 1|, median over 240 lines",
               float(np.median(errors)) * 100, "%", target="information"),
        Result("sweep phasor error |U/U_true - 1|, 95th percentile",
               float(np.percentile(errors, 95)) * 100, "%", target="information"),
        Result("sweep lines the tracker could not phase (of 240)", failed, "",
               target="0"),
    ]


def _statistics() -> list[Result]:
    """Echo statistics at the default settings (30 dB SNR, 40 dB gain, 1 V full scale)."""
    from pelvislab.sim_instruments.echo import Acoustics, Receiver, bone_echo_peak_v

    # the Python pulser: its safe state silences it (the 5077PR's keeps firing at 100 V)
    bench = _armed(generators="python", pulsers="python", seed=5)
    try:
        bench.drive.output_off()  # a still bone
        rec = bench.digitizer.acquire(5.0)[1]
        bench.pulsers[0].safe_state()  # pulser quiet: noise only
        noise = bench.digitizer.acquire(5.0)[1]
    finally:
        bench.close()
    v = rec.volts()
    vpc = rec.volts_per_count
    peak_v = bone_echo_peak_v(Acoustics(), Receiver(), FS)
    noise_rms_v = noise.volts().std()
    snr_db = 20 * math.log10(peak_v / noise_rms_v)
    x = v - v.mean(axis=1, keepdims=True)
    rho = np.sum(x[1:] * x[:-1], axis=1) / np.sqrt(np.sum(x[1:] ** 2, axis=1)
                                                   * np.sum(x[:-1] ** 2, axis=1))
    codes = rec.codes.astype(int)
    return [
        Result("SNR measured (bone echo peak envelope / noise RMS incl. quantisation)", snr_db,
               "dB", target="30 dB set"),
        Result("correlation of successive echoes (still bone), mean", float(rho.mean()), "",
               target="information"),
        Result("bone echo peak / quantiser half range (median over echoes)",
               float(np.median(np.abs(codes).max(axis=1))) / 128, "", target="0.4-0.75"),
        Result("clipped samples (codes at -128 or 127)",
               float(np.mean((codes == 127) | (codes == -128))) * 100, "%", target="0"),
        Result("noise RMS in LSB", noise_rms_v / vpc, "LSB", target="information"),
    ]


def run() -> list[Result]:
    """All simulated-bench figures."""
    return _step_results() + _statistics() + _sweep_results()
