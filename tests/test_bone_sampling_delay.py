"""An echo samples the bone when the pulse reaches it, half the round trip after the pulse.

The simulated bench moves the bone at that instant (sim_instruments/world.py) and the
runner refers the displacement phasor back to the first pulse with the tracked echo's own
round trip (acquisition/frf_lines.bone_sampling_delay_s). Taken at the pulse instead, the
phasor turns by omega * depth / c: 0.031 rad at 250 Hz under 30 mm of tissue.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.acquisition.runner import process_channel
from pelvislab.acquisition.session import ChannelData
from pelvislab.sim_instruments.bench import open_simulated_bench
from pelvislab.tests.sim_tracking_helper import phasor, track

PRF, FS, C = 5000.0, 500e6, 1540.0
DEPTH_M = 0.03
F_HZ = 250.0


def _record_at_depth():
    with open_simulated_bench(generators="python", seed=5, bone_depth_m=DEPTH_M,
                              snr_db=40.0) as b:
        for pulser in b.pulsers:
            pulser.configure(50.0, "low", 50.0, None, None)
        b.trigger.configure_pulse_burst(PRF, 2000, 1e-6, 5.0)
        record_delay_s = 2 * DEPTH_M / C - 0.5e-6  # the bone echo mid-record
        b.digitizer.configure_sequence([1], FS, 500, 2000, record_delay_s, 1.0)
        b.drive.configure_sine(F_HZ, 2.0)
        b.drive.output_on()
        b.trigger.output_on()
        records = b.digitizer.acquire(5.0)
        truth = b.world.truth[-1]
    r = records[1]
    channel = ChannelData(name="ch1", codes=r.codes, trigger_offset_s=r.trigger_offset_s,
                          sample_rate_hz=r.sample_rate_hz, prf_hz=PRF, delay_s=r.delay_s,
                          volts_per_count=r.volts_per_count, volts_offset=r.volts_offset,
                          speed_of_sound_m_s=C, output=None)
    return process_channel(channel, F_HZ), complex(truth.measured_phasor_m[1]), r


def test_phasor_of_a_deep_bone_refers_to_the_first_pulse():
    channel, truth, record = _record_at_depth()
    one_way_s = DEPTH_M / C
    turn_rad = 2 * np.pi * F_HZ * one_way_s  # what the pulse instant would leave: 0.031
    # the simulator on its own (the tests' independent tracker, phasor at the pulse
    # instants): its echoes report the bone one way later, a phase LEAD of omega*d/c for
    # x(t) = Re(X e^{+i w t}); this pins the sign, which the runner then undoes
    at_pulses = phasor(track(record, C), PRF, F_HZ)
    assert np.angle(at_pulses / truth) == pytest.approx(turn_rad, abs=0.2 * turn_rad)
    assert channel.quality["ok"] is True
    assert channel.quality["bone_sampling_delay_s"] == pytest.approx(one_way_s, abs=0.1e-6)
    ratio = channel.phasor_m / truth
    assert abs(np.angle(ratio)) < 0.2 * turn_rad
    assert abs(abs(ratio) - 1) < 0.01
