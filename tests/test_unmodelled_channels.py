"""A /frf file with a channel on no modelled bone (design 4.1: bone ``""``, e.g. an extra
pick-up on the bed frame): ``identify`` leaves it out of the fit and says so, ``gap
diagnose`` leaves it out of the ``where`` shares and says so (contract audit: identify
refused the whole file, gap listed the channel with share 0.0, which reads "fits
perfectly").

The files are ``tests/data/demo_sim_seed1.h5`` (a simulated-chain session's /frf) with one
channel added by a minimal h5py writer here (not ``write_frf``), from the text of design
4.2: the bed-frame channel's FRF is arbitrary, since nothing may use it.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from pelvislab.app.cli import main

DATA = Path(__file__).parent / "data" / "demo_sim_seed1.h5"
EXTRA = "bed_frame_z"
PARAMS = "k_io_R,k_pubs,c_pub"  # a few parameters keep the identifications short


def with_channel_on_no_bone(dst: Path, side: str = "output", every_output: bool = False
                            ) -> Path:
    """``DATA`` with one more ``side`` ("output" or "input") channel on bone "" (the bed
    frame, measured at every line: random values, H_std 1e-8 m/N); ``every_output``:
    instead, every output's bone is written "" ."""
    shutil.copy(DATA, dst)
    with h5py.File(dst, "r+") as h:
        g = h["frf"]
        text = h5py.string_dtype()

        def rewrite(group: h5py.Group, key: str, values: object, dtype: object = None) -> None:
            del group[key]
            group.create_dataset(key, data=values, dtype=dtype)

        def strings(group: h5py.Group, key: str) -> list[str]:
            return [v.decode() if isinstance(v, bytes) else str(v) for v in group[key][()]]

        if every_output:
            n = g["outputs/name"].shape[0]
            rewrite(g["outputs"], "bone", np.array([""] * n, dtype=object), text)
            return dst
        H, H_std = g["H"][()], g["H_std"][()]
        axis = 1 if side == "output" else 2
        shape = list(H.shape)
        shape[axis] = 1
        rng = np.random.default_rng(7)
        extra = (rng.normal(size=shape) + 1j * rng.normal(size=shape)) * 1e-7
        rewrite(g, "H", np.concatenate([H, extra], axis=axis))
        rewrite(g, "H_std", np.concatenate([H_std, np.full(shape, 1e-8)], axis=axis))
        group = g[f"{side}s"]
        rewrite(group, "name", np.array(strings(group, "name") + [EXTRA], dtype=object), text)
        rewrite(group, "bone", np.array(strings(group, "bone") + [""], dtype=object), text)
        rewrite(group, "position_m", np.vstack([group["position_m"][()], [0.0, 0.0, -0.3]]))
        rewrite(group, "direction", np.vstack([group["direction"][()], [0.0, 0.0, 1.0]]))
    return dst


def run(argv: list[str]) -> tuple[int, str, str]:
    """``pelvislab ARGV``: exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def identified_without_extra(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("plain") / "i.json"
    assert run(["identify", str(DATA), "--params", PARAMS, "--json", str(out)])[0] == 0
    return json.loads(out.read_text())


@pytest.mark.parametrize("side", ["output", "input"])
def test_identify_leaves_a_channel_on_no_bone_out_and_names_it(tmp_path, side,
                                                              identified_without_extra):
    src = with_channel_on_no_bone(tmp_path / "f.h5", side)
    out = tmp_path / "i.json"
    code, _, err = run(["identify", str(src), "--params", PARAMS, "--json", str(out)])
    assert code == 0, err
    doc = json.loads(out.read_text())
    notes = [n for n in doc.get("notes", []) if EXTRA in n]
    assert len(notes) == 1 and f"{side} {EXTRA}" in notes[0]
    assert "no modelled bone" in notes[0] and "left out of the fit" in notes[0]
    assert f"note: {notes[0]}" in err
    # left out, not fitted: the same values as from the file without it
    for name, entry in identified_without_extra["parameters"].items():
        assert doc["parameters"][name]["value"] == pytest.approx(entry["value"], rel=1e-9)


def test_identify_refuses_when_nothing_usable_is_left_and_says_why(tmp_path):
    src = with_channel_on_no_bone(tmp_path / "f.h5", every_output=True)
    out = tmp_path / "i.json"
    code, _, err = run(["identify", str(src), "--json", str(out)])
    assert code == 1 and not out.exists()
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "nothing left to identify" in err and "every output is on no modelled bone" in err


def test_gui_identification_pane_shows_the_note(tmp_path, qtbot):
    from pelvislab.app.commands.identify import identify_file
    from pelvislab.app.gui_replay import ReplayView

    report = identify_file(with_channel_on_no_bone(tmp_path / "f.h5"),
                           params=PARAMS.split(","))
    assert EXTRA not in report.frf.outputs.name  # the measured-vs-model curves: fitted FRFs
    view = ReplayView()
    qtbot.addWidget(view)
    view.show_identification(report)
    text = view.ident_summary.text()
    assert "note: left out of the fit" in text and f"output {EXTRA}" in text


@pytest.fixture(scope="module")
def gap_run(tmp_path_factory) -> tuple[int, str, str, dict]:
    """``gap diagnose`` of the file with the bed-frame output (one effect keeps it short:
    the shares come from the base fit)."""
    folder = tmp_path_factory.mktemp("gap")
    src = with_channel_on_no_bone(folder / "f.h5")
    out = folder / "g.json"
    code, stdout, stderr = run(["gap", "diagnose", str(src), "--json", str(out), "--no-plots",
                                "--effects", "added_mass", "--jobs", "2"])
    return code, stdout, stderr, json.loads(out.read_text()) if out.exists() else {}


def test_gap_leaves_a_channel_on_no_bone_out_of_the_shares_and_names_it(gap_run):
    code, stdout, stderr, doc = gap_run
    assert code == 0, stderr
    where = doc["where"]
    assert EXTRA not in [o["name"] for o in where["outputs"]]
    assert "" not in [b["bone"] for b in where["bones"]]
    assert all(o["share"] > 0 for o in where["outputs"])
    assert where["left_out"] == [{"side": "output", "name": EXTRA, "bone": "",
                                  "reason": "on no modelled bone"}]
    notes = [n for n in doc.get("notes", []) if EXTRA in n]
    assert len(notes) == 1 and "no modelled bone" in notes[0]
    assert f"note: {notes[0]}" in stderr
    assert f"left out (no share): output {EXTRA} (on no modelled bone)" in stdout
    # nor a COMAC (it was listed with null), nor a measured direction of the rigidity
    assert EXTRA not in [c["name"] for c in where["comac"]]
    n_modelled = len(where["outputs"])
    assert where["rigidity"]["global_note"].startswith(
        f"not determined: {n_modelled} output directions"), where["rigidity"]


def test_gui_gap_pane_shows_the_note_and_no_share_for_it(gap_run, qtbot):
    from pelvislab.app.commands.gap import GapReport
    from pelvislab.app.gui_replay import ReplayView

    doc = gap_run[3]
    view = ReplayView()
    qtbot.addWidget(view)
    view.show_gap(GapReport(doc, None, [], np.array([]), None))
    text = view.gap_summary.text()
    assert f"note: left out of the diagnosis and of the where shares: output {EXTRA}" in text
    assert "(no bone)" not in text and f"{EXTRA} (0 %)" not in text
