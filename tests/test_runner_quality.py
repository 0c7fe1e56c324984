"""The tracker's own words about a failed step reach the step's quality message."""

from __future__ import annotations

import numpy as np

from pelvislab.acquisition.runner import process_channel
from pelvislab.acquisition.session import ChannelData
from pelvislab.tests.echo_synth import synth_echoes

FS, C, PRF = 500e6, 1540.0, 5000.0


def _channel(displacement_m: np.ndarray) -> ChannelData:
    codes, offsets = synth_echoes(0.5e-6 - 2.0 * displacement_m / C, snr_db=30.0,
                                  rng=np.random.default_rng(3))
    return ChannelData(name="ch1", codes=codes, trigger_offset_s=offsets, sample_rate_hz=FS,
                       prf_hz=PRF, delay_s=0.0, volts_per_count=1.0, volts_offset=0.0,
                       speed_of_sound_m_s=C, output=None)


def _processed_sine(amplitude_m: float, frequency_hz: float, n_pulses: int = 2000
                    ) -> ChannelData:
    """A channel tracking a sine motion of the bone, processed as a run step's."""
    d = amplitude_m * np.sin(2 * np.pi * frequency_hz * np.arange(n_pulses) / PRF)
    return process_channel(_channel(d), frequency_hz)


def test_echo_leaving_the_record_is_named_in_the_quality_message():
    # 900 um peak-to-peak at 5 Hz: the echo leaves the 1 us record at both extremes.
    channel = _processed_sine(450e-6, 5.0)
    assert channel.quality["ok"] is False
    assert "left the recorded window" in channel.quality["message"]
    assert "left the recorded window" in channel.quality["tracking_warnings"]


def test_good_step_keeps_a_plain_ok_message():
    channel = _processed_sine(1e-6, 80.0)
    assert channel.quality["ok"] is True
    assert channel.quality["message"] == "ok"


def test_a_record_shorter_than_a_drive_period_is_not_ok():
    # tracking review, session 36: a truncated acquisition of 20 pulses (0.32 periods at
    # 80 Hz) gave 18 um for 1 um, "ok"
    channel = _processed_sine(1e-6, 80.0, n_pulses=20)
    assert channel.quality["ok"] is False
    assert "span 0.3 period(s) of the drive" in channel.quality["message"]
    assert "truncated acquisition" in channel.quality["message"]
    whole = _processed_sine(1e-6, 80.0, n_pulses=80)  # 1.26 periods
    assert whole.quality["ok"] is True, whole.quality


def test_a_full_record_whose_echoes_were_lost_is_not_called_truncated():
    # audit, session 41: a nine-point step at 10 Hz (5000 pulses, most echoes out of the
    # window) said "5000 segments recorded: a truncated acquisition?"
    d = 1e-6 * np.sin(2 * np.pi * 80.0 * np.arange(2000) / PRF)
    channel = _channel(d)
    channel.codes[50:] = 0  # the echo gone after 50 pulses (0.8 periods at 80 Hz)
    processed = process_channel(channel, 80.0)
    message = processed.quality["message"]
    assert processed.quality["ok"] is False
    assert "period(s) of the drive" in message and "truncated" not in message, message
    assert "the record spans 32 periods;" in message, message
    assert "50 of 2000 echoes tracked" in message, message
