"""Result files: refused before the work when they cannot be written, readable by others."""

from __future__ import annotations

import json
import os
import stat

import pytest

from pelvislab.app.commands._common import check_new_output, write_json
from pelvislab.app.commands.gap import plot_paths


def test_result_json_gets_the_users_usual_permissions(tmp_path):
    umask = os.umask(0o022)
    try:
        path = write_json(tmp_path / "r.json", {"a": 1})
    finally:
        os.umask(umask)
    # mkstemp's 0600 made identify/gap results unreadable to the rest of the lab
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    assert json.loads(path.read_text()) == {"a": 1}
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc")
def test_output_folder_that_cannot_be_written_is_refused_at_once():
    with pytest.raises(PermissionError, match="cannot write in the output folder"):
        check_new_output("/proc/self/g.json")


def test_gap_diagnose_refuses_an_existing_plot_before_the_diagnosis(tmp_path, capsys):
    from pelvislab.app.cli import main

    out = tmp_path / "g.json"
    residual, _worst = plot_paths(out)
    residual.write_text("an older plot")
    # the session file does not even exist: the plot is refused first, in a moment
    code = main(["gap", "diagnose", str(tmp_path / "missing.h5"), "--json", str(out)])
    assert code == 1
    assert "g_residual_map.png exists; not overwriting" in capsys.readouterr().err
    assert residual.read_text() == "an older plot" and not out.exists()


@pytest.mark.parametrize("argv", [
    ["import-uff", "{missing}", "--out", "{nodir}/x.h5"],
    ["model", "frf", "--points", "sacrum_x", "--out", "{nodir}/m.h5"],
    ["export-uff", "{missing}", "{nodir}/x.uff"],
    ["ema", "{missing}", "--json", "{nodir}/e.json"],
    ["gap", "benchmark", "--json", "{nodir}/b.json", "--cases", "1"],  # it made the folders
])
def test_missing_output_folder_is_said_plainly_before_any_work(tmp_path, capsys, argv):
    """Helper review, session 34: these commands did the work first, then failed with
    h5py's "unable to synchronously create file (... o_flags = 242)" or named an
    internal ``.part`` file; the input does not even exist here, so the output is checked
    first."""
    from pelvislab.app.cli import main

    values = {"missing": str(tmp_path / "missing.h5"), "nodir": str(tmp_path / "nodir")}
    code = main([a.format(**values) for a in argv])
    err = capsys.readouterr().err
    assert code == 1
    assert f"output folder {tmp_path / 'nodir'} does not exist" in err, err
    assert not (tmp_path / "nodir").exists()


def test_frf_and_uff_files_appear_only_complete_and_never_over_another(tmp_path,
                                                                       monkeypatch):
    """write_frf and write_uff write under a hidden name and publish the finished file
    without replacing one that appeared meanwhile (the UFF writer's rename replaced it)."""
    import numpy as np

    from pelvislab.acquisition import uff as uff_module
    from pelvislab.acquisition.frfset import Channels, FrfSet, read_frf, write_frf

    ch = Channels(["sacrum_x"], ["sacrum"], np.zeros((1, 3)), np.array([[1.0, 0, 0]]))
    f = np.arange(10.0, 20.0)
    frf = FrfSet(f, (1e-6 / f)[:, None, None] * np.ones((f.size, 1, 1), complex), ch, ch)
    write_frf(tmp_path / "a.h5", frf)
    assert np.array_equal(read_frf(tmp_path / "a.h5").H, frf.H)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5"]  # no temporary left

    # another process creates the name while the UFF is being written: it is kept
    target = tmp_path / "b.uff"
    real = uff_module.uff_datasets

    def and_meanwhile(*args, **kwargs):
        target.write_text("someone else's file")
        return real(*args, **kwargs)

    monkeypatch.setattr(uff_module, "uff_datasets", and_meanwhile)
    with pytest.raises(FileExistsError):
        uff_module.write_uff(target, frf)
    assert target.read_text() == "someone else's file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5", "b.uff"]


def test_a_reader_that_stops_early_ends_the_command_quietly():
    # `pelvislab model frf ... | head -c 10` said "error: [Errno 32] Broken pipe", exit 1
    # (first-day review, session 39): as a shell tool, quiet, 128 + SIGPIPE
    import subprocess
    import sys

    proc = subprocess.Popen(
        [sys.executable, "-m", "pelvislab.app", "model", "frf", "--points",
         "sacrum_x,SIAS_R_x,SIAS_L_x", "--json", "--step-hz", "0.05"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout.read(10).startswith(b"{")
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141, err
    assert "Broken pipe" not in err and "error" not in err, err
