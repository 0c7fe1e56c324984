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
