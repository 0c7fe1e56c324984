"""The blind judge-like generator writes files the product reads, with visible effects.

No diagnosis is run here (that is ``python -m pelvislab.tests.judge_like_generator OUT
--run``); this only checks the file layout (design 4.2) through the product's reader and
that an effect file differs from its no-effect twin (same subject, grid and noise draw)
by at least 3 sigma rms over the measured lines.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from pelvislab.acquisition.frfset import read_frf
from pelvislab.tests import judge_like_generator as g


@pytest.mark.parametrize(("kind", "layout", "seed"), [
    ("added_mass", "face_down", 3),
    ("sensor_misorientation", "face_up", 4),
    ("missing_ligament", "nine_point", 5),
])
def test_files_read_back_and_effect_is_visible(tmp_path, kind, layout, seed):
    s = g.make_set(np.random.default_rng(seed), kind, layout)
    s["write_std"] = True
    truth = g.write_set(s, tmp_path / "eff.h5")
    g.write_set(s, tmp_path / "twin.h5", twin=True)
    eff, twin = read_frf(tmp_path / "eff.h5"), read_frf(tmp_path / "twin.h5")

    assert truth["effect"] == kind
    assert json.loads((tmp_path / "eff.truth.json").read_text())["effect"] == kind
    assert json.loads((tmp_path / "twin.truth.json").read_text())["effect"] == "none"
    assert eff.outputs.name == [o["name"] for o in s["outputs"]]
    assert eff.inputs.name == [i["name"] for i in s["inputs"]]
    assert np.array_equal(eff.measured[0], s["mask"])
    assert np.array_equal(eff.measured, twin.measured)
    assert eff.H.shape == (s["freqs"].size, len(s["outputs"]), len(s["inputs"]))
    assert eff.H_std is not None
    m = eff.measured
    rms = np.sqrt(np.mean((np.abs(eff.H - twin.H)[m] / eff.H_std[m]) ** 2))
    assert rms >= 3.0
    assert rms == pytest.approx(s["rms_sigma"], rel=1e-9)


def test_layout_counts_and_optional_std(tmp_path):
    counts = {lay: int(g.load_layout(lay)[2].sum()) for lay in g.LAYOUTS}
    assert counts == {"face_up": 15, "face_down": 8, "nine_point": 10}
    s = g.make_set(np.random.default_rng(1), "none", "face_up")
    s["write_std"] = False
    g.write_set(s, tmp_path / "none.h5")
    frf = read_frf(tmp_path / "none.h5")
    assert frf.H_std is None
    assert 5.0 <= frf.frequency_hz[0] and frf.frequency_hz[-1] <= 300.0
