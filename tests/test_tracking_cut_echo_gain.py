"""Echoes whose tail crosses the record's end: no step between cut and uncut echoes.

The simulated face_up session showed a gain error of -0.02 to -0.045 % on lines moving
20-40 um (many sigma of those lines' noise): the echo sits late in the record, its tail leaves
the record at the far extreme of the motion, and the cut echoes (in-record least-squares
delay, unfiltered reference) were ~0.01-0.02 sample off the scale of the uncut ones (normal
fine pass, band-passed reference). ``tracking._cut_calibration`` measures that offset.
"""

from __future__ import annotations

import numpy as np

from pelvislab.acquisition.phasor import estimate_phasor
from pelvislab.acquisition.tracking import track_echoes
from pelvislab.tests.echo_synth import synth_echoes

FS = 500e6
C = 1540.0
PRF = 5000.0
SAMPLE_M = C / 2 / FS  # displacement per sample of delay, m


def test_echo_tail_crossing_the_record_end_leaves_no_gain_error():
    # Echo centre at sample 350 of 500: its gate reaches the record's end (minus the lag
    # range), so moving 40 um away (52 samples later) cuts its tail. Noise-free, unquantised.
    n, f_hz, amp_m = 2000, 10.0, 40e-6
    t = np.arange(n) / PRF
    d = amp_m * np.sin(2 * np.pi * f_hz * t + 0.3)
    arrival = 0.7e-6 - 2.0 * d / C
    codes, off = synth_echoes(arrival, snr_db=None, quantise=False,
                              rng=np.random.default_rng(14))
    res = track_echoes(codes, off, FS, C)
    assert not res.lost.any()
    err = res.displacement_m - (d - d[0])
    late = arrival > np.percentile(arrival, 80)  # the cut echoes
    step_samples = (err[late].mean() - err[~late].mean()) / SAMPLE_M
    gain = abs(estimate_phasor(res.displacement_m, t, f_hz).value) / amp_m - 1.0
    # before the calibration: step 0.0085 sample, gain -0.019 %; after: -0.0002, +0.0005 %
    assert abs(step_samples) < 0.002
    assert abs(gain) < 5e-5
