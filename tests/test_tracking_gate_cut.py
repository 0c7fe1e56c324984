"""A gate set by hand that cuts the echo is named in the tracker's notes.

A gate typed at a prompt, dragged on the A-scan, given to ``reprocess --gate`` or written in
a protocol is the operator's. One that ended at the echo's peak gave every step ``ok`` with
about 5x the displacement noise (the simulated demo session re-tracked so: H_std 5.0x,
|H| off by tens of % at the high lines), and nothing said so.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.acquisition.tracking import (
    GATE_CUT_LEVEL,
    TrackingOptions,
    _cut_echo_note,
    gate_preview,
    track_echoes,
)
from pelvislab.tests.echo_synth import synth_echoes

FS = 500e6
C = 1540.0
PRF = 5e3
FREQUENCY_HZ = 250.0


def _record(seed: int, n: int = 1000, extra=()):
    """0.2 um at 250 Hz, echo centred at sample 300 of 600 (its envelope at 10 % +-134
    samples), 30 dB."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / PRF
    d = 0.2e-6 * np.sin(2 * np.pi * FREQUENCY_HZ * t)
    codes, off = synth_echoes(300 / FS - 2 * d / C, n_samples=600, amplitude_counts=60.0,
                              snr_db=30, extra_echoes=extra, rng=rng)
    return codes, off, t


def _noise_m(res, t) -> float:
    """SD (m) of the tracked displacement about its fitted sine."""
    ok = ~res.lost
    basis = np.c_[np.sin(2 * np.pi * FREQUENCY_HZ * t), np.cos(2 * np.pi * FREQUENCY_HZ * t),
                  np.ones(t.size)][ok]
    coef, *_ = np.linalg.lstsq(basis, res.displacement_m[ok], rcond=None)
    return float(np.std(res.displacement_m[ok] - basis @ coef))


def _cut_notes(res) -> list[str]:
    return [w for w in res.warnings if w.startswith("gate (")]


def test_a_gate_ending_at_the_peak_is_named_and_is_why():
    noise = {}
    for seed in range(3):
        codes, off, t = _record(seed)
        whole = track_echoes(codes, off, FS, C, options=TrackingOptions(gate=(160, 440)))
        half = track_echoes(codes, off, FS, C, options=TrackingOptions(gate=(160, 300)))
        assert not _cut_notes(whole), whole.warnings
        notes = _cut_notes(half)
        assert len(notes) == 1, half.warnings
        assert notes[0].startswith("gate (160, 300): the gate holds only a flank of the echo "
                                   "whose envelope peaks at sample 30")
        assert "at the gate's stop (sample 300)" in notes[0]
        noise.setdefault("whole", []).append(_noise_m(whole, t))
        noise.setdefault("half", []).append(_noise_m(half, t))
    # the reason for the note (measured 4.9x over 4 seeds); each step is still `ok`
    assert np.mean(noise["half"]) > 3.0 * np.mean(noise["whole"])
    assert not half.lost.any()


@pytest.mark.parametrize("gate, edges", [
    ((270, 330), ("start (sample 270)", "stop (sample 330)")),  # ~90 % both sides
    ((230, 370), ("start (sample 230)", "stop (sample 370)")),  # ~56 %
    ((160, 340), ("stop (sample 340)",)),                       # ~80 % at its stop only
    ((380, 480), ("start (sample 380)",)),  # the tail only (~45 %): a flank
])
def test_the_note_names_each_edge_through_the_echo(gate, edges):
    codes, off, _ = _record(0, n=64)
    notes = gate_preview(codes, FS, TrackingOptions(gate=gate)).notes
    assert len(notes) == 1, notes
    for edge in edges:
        assert f"at the gate's {edge}" in notes[0]
    assert notes[0].count("at the gate's") == len(edges)


@pytest.mark.parametrize("gate", [(160, 440), (200, 400), (20, 120), (480, 580)])
def test_no_note_on_the_whole_echo_nor_on_a_gate_away_from_it(gate):
    # +-100 samples: the envelope at 25 %; a gate on noise alone is not this note's case
    codes, off, _ = _record(0, n=64)
    assert gate_preview(codes, FS, TrackingOptions(gate=gate)).notes == []


@pytest.mark.parametrize("snr_db", [30.0, 20.0, 15.0])
def test_a_gate_on_noise_is_not_judged_at_any_seed(snr_db):
    # seed 0 passed; on 7-15 of 40 seeds the walk uphill from a noise peak at the gate's
    # edge reached the bone echo: "holds only a flank ... 2 % of that peak" (review)
    noted = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        codes, _ = synth_echoes(np.full(16, 300 / FS), n_samples=600, amplitude_counts=60.0,
                                snr_db=snr_db, rng=rng)
        for gate in ((20, 120), (480, 580)):
            noted += bool(gate_preview(codes, FS, TrackingOptions(gate=gate)).notes)
    assert noted == 0


def test_first_segments_constant_at_a_code_still_track_in_a_hand_gate():
    # empty segments at -1 (not 0) among the first 64: the note's envelope raised "the
    # first echoes are flat" and the channel failed where it had tracked (review)
    codes, off, t = _record(0)
    codes = codes.astype(np.int16)
    codes[:64] = -1
    res = track_echoes(codes, off, FS, C, options=TrackingOptions(gate=(160, 440)))
    assert res.lost[:64].all() and not res.lost[64:].any()


def test_the_automatic_gate_is_not_judged_so():
    codes, off, _ = _record(0, n=64)
    preview = gate_preview(codes, FS)
    assert preview.notes == [] and preview.gate[0] < 170 and preview.gate[1] > 430


def test_an_edge_on_a_neighbouring_echo_is_not_a_cut():
    # a second echo 0.6 us later (300 samples: its own lump beyond a dip) at 0.8x; a gate
    # that stops on its rising flank keeps the bone echo whole
    env = (np.exp(-0.5 * ((np.arange(800) - 300) / 60.0) ** 2)
           + 0.8 * np.exp(-0.5 * ((np.arange(800) - 600) / 60.0) ** 2))
    assert _cut_echo_note(env, (160, 560)) == ""  # 0.8 x 53 % at 560: on the other echo
    assert "the gate cuts the echo" in _cut_echo_note(env, (160, 320))
    # the level rule itself
    level = float(np.exp(-0.5 * (49 / 60.0) ** 2))
    assert level > GATE_CUT_LEVEL
    assert "the gate cuts the echo" in _cut_echo_note(env, (160, 350))
    assert _cut_echo_note(env, (160, 380)) == ""  # 41 %


def test_reprocess_says_once_per_channel_that_its_gate_cuts_the_echo(tmp_path, capsys):
    from pelvislab.acquisition.session import SessionReader
    from pelvislab.app.cli import main
    from pelvislab.tests.test_runner_control import make_bench, prepare

    with prepare(tmp_path, make_bench()) as session:  # 8 steps, echoes peaking at sample 76
        assert session.run().status == "completed"
    out = tmp_path / "cut.h5"
    code = main(["reprocess", str(tmp_path / "s.h5"), "--out", str(out),
                 "--gate", "ch1=20:76"])
    err = capsys.readouterr().err
    assert code == 0, err
    notes = [line for line in err.splitlines() if line.startswith("note: ")]
    assert len(notes) == 1, err  # not one per step; ch2's automatic gate has none
    assert notes[0].startswith("note: ch1, 8 of its 8 steps: gate (20, 76): the gate holds "
                               "only a flank of the echo")
    with SessionReader(out) as reader:
        # (the log cuts its lines at 256 bytes)
        assert any(line.startswith("ch1, 8 of its 8 steps: gate (20, 76): the gate holds")
                   for line in reader.log_lines())
        steps = list(reader.steps(with_echoes=False))
    ch1 = [c.quality for s in steps for c in s.channels if c.name == "ch1"]
    assert all(q["ok"] and "holds only a flank" in q["tracking_warnings"] for q in ch1)
    # the whole echo gated by hand: nothing to say
    code = main(["reprocess", str(tmp_path / "s.h5"), "--out", str(tmp_path / "whole.h5"),
                 "--gate", "ch1=12:148"])
    assert code == 0 and "note:" not in capsys.readouterr().err
