"""`pelvislab demo` stopped by the operator during its run stage (helper review, session 34:
it printed "FAILED with exit code 130", skipped the rest as if no session existed, said
"demo finished" and exited 1, while 133 of 308 steps were kept on disk)."""

from __future__ import annotations

from pelvislab.app.cli import main
from pelvislab.app.commands import run as run_module


def test_interrupted_run_stage_stops_the_demo_with_130_and_names_the_kept_session(
        tmp_path, monkeypatch, capsys):
    calls = []

    def interrupted_run(args):  # what run_command returns after Ctrl-C: the file is kept
        calls.append(args.out)
        open(args.out, "wb").close()
        print("pelvislab run: interrupted: interrupted by Ctrl-C (SIGINT); outputs off")
        return 130

    monkeypatch.setattr(run_module, "run_command", interrupted_run)
    code = main(["demo", "--out", str(tmp_path / "demo")])
    out, err = capsys.readouterr()
    assert code == 130
    assert len(calls) == 1
    assert "interrupted: the demo stops here" in err and "--resume" in err
    assert "FAILED" not in out + err
    assert "identify" not in out.split("simulated session")[1]  # no later stage started
    assert "demo finished" not in out


def test_out_naming_a_file_is_refused_plainly(tmp_path, capsys):
    target = tmp_path / "demo.h5"
    target.write_text("not a folder")
    assert main(["demo", "--out", str(target)]) == 1
    assert "exists and is not a folder" in capsys.readouterr().err
    assert target.read_text() == "not a folder"
