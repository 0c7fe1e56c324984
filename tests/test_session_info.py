"""``pelvislab session info``: a session's or FRF-only file's content at a glance, read from
files the simulated bench writes (a complete run, a run aborted in its second setup, a run
whose outputs could not be confirmed off) and from an FRF-only file."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from pelvislab.acquisition.runner import SetupStarted, prepare_session
from pelvislab.acquisition.session import process_identity
from pelvislab.acquisition.session_info import session_info
from pelvislab.app.cli import main

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")

DATA = Path(__file__).parent / "data"

PROTOCOL = """
schema = "pelvislab-protocol"
schema_version = 1
name = "info-test"
[subject]
id = "S017"
[sweep]
frequencies_hz = [60.0, 120.0, 180.0]
drive_vpp = 0.2
settle_s = 0.02
[ultrasound]
pulses = 300
samples = 500
[[setups]]
name = "a"
excitation = "SIAS_R_x"
transducers = { ch1 = "SIAS_R_x", ch2 = "sacrum_x" }
[[setups]]
name = "b"
excitation = "SIAS_L_x"
transducers = { ch1 = "SIPS_R_x", ch2 = "SIPS_L_x" }
"""


def _run(folder: Path, abort_in_setup: int | None = None) -> Path:
    protocol = folder / "p.toml"
    protocol.write_text(PROTOCOL)
    out = folder / "s.h5"
    bench = sim_bench.open_simulated_bench(generators="python")
    with prepare_session(protocol, out, bench=bench) as session:
        runner = session.runner

        def listen(event: object) -> None:
            if isinstance(event, SetupStarted) and event.setup_index == abort_in_setup:
                runner.abort("test: stopped in the second setup")

        runner.subscribe(listen)
        session.run()
    return out


@pytest.fixture(scope="module")
def complete_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _run(tmp_path_factory.mktemp("complete"))


def test_a_complete_session_is_summarised_against_its_plan(complete_session: Path) -> None:
    info = session_info(complete_session)
    assert info["kind"] == "session" and info["status"] == "completed"
    assert info["subject_id"] == "S017" and info["protocol_name"] == "info-test"
    assert info["outputs_confirmed_off"] is True
    assert [r["status"] for r in info["runs"]] == ["completed"]
    assert info["runs"][0]["simulated"] is True
    steps = info["steps"]
    assert (steps["planned"], steps["acquired"], steps["incomplete"], steps["damaged"]) == \
        (6, 6, 0, 0)
    assert [(s["setup"], s["acquired"], s["planned"]) for s in steps["by_setup"]] == \
        [("a", 3, 3), ("b", 3, 3)]
    assert set(info["channels"]) == {"ch1", "ch2"}
    assert info["channels"]["ch1"]["records"] == 6
    assert info["channels"]["ch1"]["gate_sources"] == {"auto": 6}
    frf = info["frf"]
    assert frf["lines"] == 3 and frf["frequency_hz"] == [60.0, 180.0]
    assert frf["pairs_planned"] == 4 and frf["pairs_measured"] == 4 and frf["h_std"]
    assert {p["name"]: p["bone"] for p in frf["outputs"]}["sacrum_x"] == "sacrum"
    json.dumps(info, allow_nan=False)  # JSON-ready as it is


def test_an_aborted_run_shows_what_the_plan_lacks(tmp_path: Path, capsys) -> None:
    info = session_info(_run(tmp_path, abort_in_setup=1))
    assert info["status"] == "aborted" and "second setup" in info["reason"]
    assert info["steps"]["planned"] == 6 and info["steps"]["acquired"] == 3
    assert [s["acquired"] for s in info["steps"]["by_setup"]] == [3, 0]
    frf = info["frf"]
    assert frf["pairs_measured"] == 2 and frf["pairs_planned"] == 4
    never = {(p["output"], p["input"]) for p in frf["pairs"] if not p["lines_measured"]}
    assert never == {("SIPS_R_x", "SIAS_L_x"), ("SIPS_L_x", "SIAS_L_x")}
    # an abort asked for, outputs off: a warning in the log, not an error (an operator's
    # STOP read "ERROR run aborted"; session 43)
    assert info["log"]["errors"] == 0 and info["log"]["warnings"] >= 1
    assert "WARNING run aborted: test: stopped in the second setup" in \
        info["log"]["latest_flagged"][-1]
    assert main(["session", "info", str(tmp_path / "s.h5")]) == 0
    text = capsys.readouterr().out
    assert "steps: 3 acquired of 6 planned" in text
    assert f"to complete it: pelvislab run {tmp_path / 'p.toml'} --out " \
        f"{tmp_path / 's.h5'} --resume" in text
    assert "SIPS_R_x/SIAS_L_x: 0 of 3 lines" in text  # planned, never measured


def test_cli_text_names_outputs_not_confirmed_off_and_the_json_is_the_same(
        complete_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    unsafe = tmp_path / "unsafe.h5"
    shutil.copy(complete_session, unsafe)
    with h5py.File(unsafe, "r+") as handle:
        handle["runs/000"].attrs["outputs_confirmed_off"] = False
    assert main(["session", "info", str(unsafe), "--json", str(tmp_path / "i.json")]) == 0
    text = capsys.readouterr().out
    assert "OUTPUTS NOT CONFIRMED OFF" in text
    assert "steps: 6 acquired of 6 planned" in text
    assert "a: drive at SIAS_R_x; ch1 SIAS_R_x, ch2 sacrum_x: 3/3" in text
    written = json.loads((tmp_path / "i.json").read_text())
    assert written["outputs_confirmed_off"] is False
    assert main(["session", "info", str(unsafe), "--json", "-"]) == 0
    assert json.loads(capsys.readouterr().out) == written
    killed = tmp_path / "killed.h5"  # what a kill -9 leaves: no end, nothing confirmed
    shutil.copy(complete_session, killed)
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    with h5py.File(killed, "r+") as handle:
        handle["runs/000"].attrs["status"] = "running"
        handle["runs/000"].attrs["pid"] = int(gone.stdout)  # a process that has ended
        del handle["runs/000"].attrs["outputs_confirmed_off"]
    assert main(["session", "info", str(killed)]) == 0
    text = capsys.readouterr().out
    assert "status: running (no end recorded" in text and "killed?" in text
    assert "may have left an output on: check the bench" in text


@pytest.mark.skipif(process_identity(os.getpid()) is None,
                    reason="needs /proc (Linux) to tell a process from a later one")
def test_a_run_whose_writer_lives_is_not_called_killed(
        complete_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """With HDF5 file locking off (NFS) a file being written opens for reading: its run
    read "killed?", with a resume command that would have made two writers. A pid alone
    is not the writer (review): after a reboot, or in time, another process holds it."""
    live = tmp_path / "live.h5"
    shutil.copy(complete_session, live)
    writer = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        boot, ticks = process_identity(writer.pid)
        with h5py.File(live, "r+") as handle:
            run = handle["runs/000"].attrs
            assert run["host"] == socket.gethostname() and run["pid"] == os.getpid()
            run["status"] = "running"
            run["pid"], run["boot_id"], run["pid_start_ticks"] = writer.pid, boot, ticks
            del run["outputs_confirmed_off"]
            del handle["steps"][sorted(handle["steps"])[-1]]  # short of its plan
        info = session_info(live)
        assert info["writer_alive"] is True and info["runs"][0]["pid"] == writer.pid
        assert main(["session", "info", str(live)]) == 0
        text = capsys.readouterr().out
        assert "is still running: being written" in text and "killed" not in text
        assert "(the run is under way)" in text and "--resume" not in text
        with h5py.File(live, "r+") as handle:  # the pid now another process's
            handle["runs/000"].attrs["pid_start_ticks"] = ticks + 1
        assert session_info(live)["writer_alive"] is False
        with h5py.File(live, "r+") as handle:  # written on another machine: cannot tell
            handle["runs/000"].attrs["pid_start_ticks"] = ticks
            handle["runs/000"].attrs["host"] = "bench-pc-7"
        assert session_info(live)["writer_alive"] is None
        assert main(["session", "info", str(live)]) == 0
        text = capsys.readouterr().out
        assert (f"killed, unless its process {writer.pid} on bench-pc-7 is still running"
                in text)
        assert "check the bench" in text
        assert f"to complete it, once process {writer.pid} on bench-pc-7 has ended: " in text
    finally:
        writer.kill()
        writer.wait()
    with h5py.File(live, "r+") as handle:
        handle["runs/000"].attrs["host"] = socket.gethostname()
    assert session_info(live)["writer_alive"] is False  # ended: killed
    for pid in ("n/a", 0, -1):  # unreadable or impossible: not known, no error
        with h5py.File(live, "r+") as handle:
            handle["runs/000"].attrs["pid"] = pid
        info = session_info(live)
        assert info["writer_alive"] is None and info["runs"][0]["pid"] is None


def test_this_processes_own_closed_file_is_not_being_written(
        complete_session: Path, tmp_path: Path) -> None:
    """The run of a file this very process wrote and closed without an end (a notebook,
    the GUI) read "still being written": the process lives, its writer does not."""
    own = tmp_path / "own.h5"
    shutil.copy(complete_session, own)
    with h5py.File(own, "r+") as handle:
        handle["runs/000"].attrs["status"] = "running"
    expected = None if process_identity(os.getpid()) is None else False
    assert session_info(own)["writer_alive"] is expected

def test_an_frf_only_file_and_a_foreign_file(tmp_path: Path, capsys) -> None:
    info = session_info(DATA / "chain_fk_seed3.h5")
    assert info["kind"] == "frf-only"
    assert info["frf"]["lines"] == 60 and info["frf"]["pairs_measured"] == 15
    assert main(["session", "info", str(DATA / "chain_fk_seed3.h5")]) == 0
    text = capsys.readouterr().out
    assert "15 pairs measured of 21 (output, input) cells" in text
    assert "0 of 60 lines" not in text  # an FRF-only file's empty cells are its layout
    foreign = tmp_path / "other.h5"
    with h5py.File(foreign, "w") as handle:
        handle["x"] = [1, 2, 3]
    assert main(["session", "info", str(foreign)]) == 1
    err = capsys.readouterr().err
    assert "not a pelvislab session" in err and "Traceback" not in err
    assert main(["session", "info", str(tmp_path)]) == 1
    assert "is a folder" in capsys.readouterr().err


def test_no_resume_is_suggested_for_a_session_whose_plan_is_unknown(tmp_path: Path,
                                                                    capsys) -> None:
    # review, session 43: a session whose stored protocol does not parse (written by
    # another program from design 4.2, /protocol "a record, not an input") was told
    # "to complete it: pelvislab run PROTOCOL.toml --out S.h5 --resume", which refuses it
    # (its /protocol must be the protocol file's text, and one that parses)
    source = _run(tmp_path, abort_in_setup=1)
    with h5py.File(source, "r+") as handle:
        handle["protocol"].attrs["toml"] = "a record, not an input"
    assert main(["session", "info", str(source)]) == 0
    text = capsys.readouterr().out
    assert "the plan is unknown" in text and "steps: 3 acquired\n" in text
    assert "to complete it" not in text


def test_the_resume_advice_names_a_protocol_file_only_if_it_holds_the_sessions_text(
        tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    # review, session 43: the advice named /protocol's `source` as recorded: a protocol
    # edited since ("its /protocol differs from p.toml") or a relative path given at the
    # run, read from another folder (not found), and `run --resume` refused it
    session = _run(tmp_path, abort_in_setup=1)
    assert session_info(session)["protocol_source_state"] == "matches"
    with h5py.File(session, "r+") as handle:
        handle["protocol"].attrs["source"] = "p.toml"  # as `run p.toml` in tmp_path records
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert session_info(session)["protocol_source_state"] == "missing"
    assert main(["session", "info", str(session)]) == 0
    text = capsys.readouterr().out
    assert "pelvislab run p.toml --out" not in text
    assert "holding the session's /protocol text exactly (p.toml is not found from here)" \
        in text
    monkeypatch.chdir(tmp_path)
    assert main(["session", "info", str(session)]) == 0  # from the run's folder: named
    assert "to complete it: pelvislab run p.toml --out" in capsys.readouterr().out
    (tmp_path / "p.toml").write_text(PROTOCOL + "\n# edited after the run\n")
    assert session_info(session)["protocol_source_state"] == "differs"
    assert main(["session", "info", str(session)]) == 0
    assert "(p.toml differs from it: edited since the run?)" in capsys.readouterr().out


def test_an_frf_file_without_h_std_is_said_what_the_analyses_do_without_it(
        tmp_path: Path, capsys) -> None:
    # review, session 43: "H_std absent (analyses estimate the noise)", what export-uff's
    # note said until this session's fix: ema estimates none, it weights each FRF by 1/RMS
    imported = tmp_path / "imported.h5"
    shutil.copy(DATA / "chain_fk_seed3.h5", imported)
    with h5py.File(imported, "r+") as handle:
        del handle["frf/H_std"]
    assert main(["session", "info", str(imported)]) == 0
    text = capsys.readouterr().out
    assert "analyses estimate the noise" not in text
    assert "H_std absent (identify and gap diagnose estimate the noise; ema weights each " \
        "FRF by 1/RMS)" in text


def test_damaged_and_unfinished_step_groups_are_counted_not_raised(
        complete_session: Path, tmp_path: Path) -> None:
    """Read from the groups' attributes alone (no displacement: 2.3 s -> 0.8 s on the demo
    session); a group a kill cut short counts as damaged, a failed one as incomplete."""
    hurt = tmp_path / "hurt.h5"
    shutil.copy(complete_session, hurt)
    with h5py.File(hurt, "r+") as handle:
        del handle["steps/000001"].attrs["setup"]  # cut short before its attributes
        handle["steps/000002"].attrs["status"] = "failed"
        handle.create_group("steps/000099")  # created, nothing written
    info = session_info(hurt)
    steps = info["steps"]
    assert (steps["groups"], steps["damaged"], steps["incomplete"], steps["acquired"]) == \
        (7, 2, 1, 4)
    assert "2 step group(s) unreadable" in " ".join(info["notes"])
    assert info["channels"]["ch1"]["records"] == 4


def test_a_run_that_recorded_no_safe_state_is_named_beside_confirmed_ones(
        complete_session: Path, tmp_path: Path, capsys) -> None:
    """A killed run resumed later: the session's outputs_confirmed_off is True (the runs
    that recorded it), which read "every run's outputs confirmed off"."""
    resumed = tmp_path / "resumed.h5"
    shutil.copy(complete_session, resumed)
    with h5py.File(resumed, "r+") as handle:
        handle.copy(handle["runs/000"], "runs/001")
        handle["runs/000"].attrs["status"] = "running"
        del handle["runs/000"].attrs["outputs_confirmed_off"]
    assert main(["session", "info", str(resumed)]) == 0
    text = capsys.readouterr().out
    assert "every run's outputs confirmed off" not in text
    assert "not recorded for run 0" in text


def test_a_design_only_session_says_its_tracking_quality_is_not_recorded(
        complete_session: Path, tmp_path: Path, capsys) -> None:
    """A session written from design 4.2 alone has no tracking quality: its records read
    "0 not ok; gates: auto N", the defaults taken for data (review, session 43)."""
    from pelvislab.tests.test_session_design_only import _design_only_copy

    foreign = tmp_path / "design.h5"
    _design_only_copy(complete_session, foreign)
    info = session_info(foreign)
    ch1 = info["channels"]["ch1"]
    assert (ch1["records"], ch1["quality_not_recorded"], ch1["quality_not_ok"]) == (6, 6, 0)
    assert ch1["gate_sources"] == {"not recorded": 6}
    assert main(["session", "info", str(foreign)]) == 0
    assert "0 not ok (6 without tracking quality)" in capsys.readouterr().out


def test_the_replay_shows_the_summary_in_its_file_tab(complete_session: Path, qtbot) -> None:
    """The GUI replay's File tab holds the same summary, read when first shown."""
    from pelvislab.app.gui_replay import ReplayView

    view = ReplayView()
    qtbot.addWidget(view)
    view.open_session(complete_session)
    assert view.file_info.toPlainText() == ""  # not read until shown
    view.tabs.setCurrentWidget(view.file_info)
    text = view.file_info.toPlainText()
    assert "steps: 6 acquired of 6 planned" in text and "status: completed" in text


def test_a_writer_dropped_without_close_is_no_longer_writing(tmp_path: Path) -> None:
    import gc

    from pelvislab.acquisition.protocol import parse_protocol
    from pelvislab.acquisition.session import SessionWriter, being_written_here
    from pelvislab.tests.test_session_format import BENCH, POINTS, TEXT

    path = tmp_path / "dropped.h5"
    writer = SessionWriter.create(path, parse_protocol(TEXT, "t.toml", None, POINTS), BENCH)
    assert being_written_here(path)
    del writer
    gc.collect()
    assert not being_written_here(path)
