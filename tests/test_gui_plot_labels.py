"""Readable FRF plots: the log axis' labels and the legend's rows (pyqtgraph, offscreen)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pelvislab.app.gui_plots import FrfPanel, log_tick_labels

MINOR = [k + math.log10(m) for k in (-1, 0, 1) for m in range(1, 10)]


def labelled(visible, scale=1.0):
    return [f"{10 ** v * scale:g}" for v, s in zip(MINOR, log_tick_labels(MINOR, visible, scale),
                                                    strict=True) if s]


def test_only_decades_are_labelled_when_two_are_in_view():
    # pyqtgraph labels every minor tick of a short log axis: 0.5 ... 30 was a column of
    # overlapping numbers (GUI review, session 35)
    assert labelled((math.log10(0.5), math.log10(30))) == ["0.1", "1", "10"]


def test_one_two_five_under_two_decades_and_every_tick_in_a_narrow_span():
    assert labelled((math.log10(2), math.log10(7))) == ["0.1", "0.2", "0.5", "1", "2", "5",
                                                        "10", "20", "50"]
    assert labelled((math.log10(2.2), math.log10(3.9))) == [
        f"{m * 10.0 ** k:g}" for k in (-1, 0, 1) for m in range(1, 10)]


def test_the_axis_prefix_scale_is_applied_before_choosing():
    # values in m/N shown in µm/N: the displayed 1, 10 (1e-6, 1e-5 m/N) are the decades
    values = [math.log10(x) for x in (1e-6, 2e-6, 5e-6, 1e-5, 3e-5)]
    labels = log_tick_labels(values, (math.log10(0.5e-6), math.log10(30e-6)), 1e6)
    assert labels == ["1", "", "", "10", ""]


@pytest.mark.parametrize("n_lines", [2, 3])
def test_each_legend_row_keeps_its_name_beside_its_line(qtbot, n_lines):
    # the legend stretched over both plots: each name sat far above its line sample
    panel = FrfPanel()
    qtbot.addWidget(panel)
    panel.resize(980, 300)
    frequency_hz = np.linspace(30, 280, 20)
    for i in range(n_lines):
        panel.show_measured(f"out{i} / in", i, frequency_hz, np.full(20, 1e-6 * (i + 1)))
    panel.show()
    qtbot.waitExposed(panel)
    qtbot.wait(50)
    for sample, label in panel.legend.items:
        centre_sample = sample.sceneBoundingRect().center().y()
        centre_label = label.item.sceneBoundingRect().center().y()  # the text itself
        assert abs(centre_sample - centre_label) < 6, (centre_sample, centre_label)


def test_the_displacement_channels_are_named_in_the_title_not_over_the_traces(qtbot):
    # the legend sat on the traces, which fill the whole box (GUI review, session 35)
    from pelvislab.app.gui_plots import CHANNEL_PENS, DisplacementPanel

    panel = DisplacementPanel()
    qtbot.addWidget(panel)
    panel.set_channels(["ch1 → SIAS_R_x", "ch2 → sacrum<x>"])
    title = panel.getPlotItem().titleLabel.text
    assert f'color:{CHANNEL_PENS[0]}">&#9632; ch1 → SIAS_R_x' in title
    assert f'color:{CHANNEL_PENS[1]}">&#9632; ch2 → sacrum&lt;x&gt;' in title
    assert panel.getPlotItem().legend is None
    panel.set_channels(["ch1 → PSIS_L"])  # a new setup renames
    assert "PSIS_L" in panel.getPlotItem().titleLabel.text
    assert "sacrum" not in panel.getPlotItem().titleLabel.text


def test_residual_map_columns_sit_at_their_own_frequencies():
    # replay review, session 36: the map's columns were spread evenly over the band, so on
    # the demo's zoomed grid the 173.75 Hz line was drawn at 109 Hz
    from pelvislab.app.gui_replay import display_columns

    f = np.concatenate([np.arange(30.0, 170.0, 10.0), np.arange(170.0, 180.0, 0.5),
                        np.arange(180.0, 301.0, 10.0)])
    index, low, high = display_columns(f)
    assert (low, high) == (25.0, 305.0)
    centres = low + (np.arange(index.size) + 0.5) * (high - low) / index.size
    for line in (0, np.flatnonzero(f == 173.5)[0], f.size - 1):
        shown = centres[index == line]
        assert shown.min() >= f[line] - 5.0 and shown.max() <= f[line] + 5.0, (f[line], shown)
        assert f[line] - 0.5 <= shown.mean() <= f[line] + 0.5
    assert set(index.tolist()) == set(range(f.size))  # every line shown
    one, lo1, hi1 = display_columns(np.array([50.0]))
    assert one.tolist() == [0] and lo1 == hi1 == 50.0


def test_echo_trace_volts_follow_the_digitizers_convention():
    # SegmentedRecord: volts = codes x volts_per_count - volts_offset (Acqiris vOffset);
    # the A-scan added the offset (twice it off with a non-zero offset)
    from types import SimpleNamespace

    import numpy as np

    from pelvislab.app.gui_plots import echo_trace
    from pelvislab.drivers.interfaces import SegmentedRecord

    codes = np.array([[0, 10, -20, 127]], dtype=np.int8)
    record = SegmentedRecord(codes=codes, trigger_offset_s=np.zeros(1), sample_rate_hz=500e6,
                             delay_s=10e-6, volts_per_count=0.004, volts_offset=0.05)
    channel = SimpleNamespace(codes=codes, delay_s=10e-6, sample_rate_hz=500e6,
                              volts_per_count=0.004, volts_offset=0.05)
    time_s, volts = echo_trace(channel, 0)
    assert np.allclose(volts, record.volts()[0])
    assert np.allclose(time_s, 10e-6 + np.arange(4) / 500e6)
