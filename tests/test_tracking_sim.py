"""Cross-check with the simulated bench's pulse-echo physics (sim_instruments/echo.py).

The simulator (another area) and the tracker were written independently against the same
timing convention (SegmentedRecord: sample k of segment s at delay_s + k/fs +
trigger_offset_s[s]) and the same sign (displacement positive toward the transducer). This
test fails if either drifts from it. Speckle, tissue attenuation and 8-bit codes included.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.acquisition.frf_lines import displacement_phasor
from pelvislab.acquisition.tracking import track_echoes

echo = pytest.importorskip("pelvislab.sim_instruments.echo")

FS, PRF, N = 500e6, 5000.0, 2000


@pytest.mark.parametrize("f_hz, amp_m", [(80.0, 2e-6), (280.0, 0.5e-6)])
def test_tracks_the_simulated_bone_echo(f_hz, amp_m):
    acoustics, receiver = echo.Acoustics(), echo.Receiver()
    rng = np.random.default_rng(int(f_hz))
    t = np.arange(N) / PRF
    X = amp_m * np.exp(0.5j)
    u = np.real(X * np.exp(2j * np.pi * f_hz * t))
    off = -rng.uniform(0.0, 1.0 / FS, N)
    c = acoustics.speed_of_sound_m_s
    delay = 2 * acoustics.bone_depth_m / c - 0.5e-6  # bone echo mid-record
    codes, vpc = echo.synthesize_channel(acoustics, receiver, u, off, sample_rate_hz=FS,
                                         n_samples=500, delay_s=delay, full_scale_v=1.0,
                                         rng=rng)
    res = track_echoes(codes, off, FS, c, vpc)
    assert not res.lost.any()
    err = res.displacement_m - (u - u[0])
    assert np.std(err) < 0.25e-6  # per-echo jitter at the simulator's 30 dB
    p = displacement_phasor(res, PRF, f_hz)
    assert abs(p.value - X) < 5 * p.std
    assert abs(np.median(res.snr_db) - receiver.snr_db) < 3.0
