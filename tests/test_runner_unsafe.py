"""An output the bench cannot switch off is never reported as "outputs off".

The drivers' safe state logs a failed ``OUTP OFF`` and does not raise (the other outputs
must still go off), so the bench, the runner, the session file, the CLI and the GUI each
have to look at what it logged. Checked against the simulator's own output state. Also:
a disk that fills up ends the run as a fault before a write fails.
"""

from __future__ import annotations

import argparse

import pytest

from pelvislab.acquisition import runner as runner_module
from pelvislab.acquisition.runner import prepare_session
from pelvislab.acquisition.session import SessionReader

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")
faults = pytest.importorskip("pelvislab.sim_instruments.faults")

# the kill tests' two-setup, 8-step protocol (drive command 22 comes after OUTP ON)
from pelvislab.tests.test_runner_kill import PROTOCOL  # noqa: E402


def _bench(fault):
    return sim_bench.open_simulated_bench(generators="python", faults=[fault])


def _run_with(tmp_path, fault):
    """(final event, prepared session, bench) of the protocol run with ``fault``."""
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    bench = _bench(fault)
    with prepare_session(protocol, tmp_path / "s.h5", bench=bench) as session:
        final = session.run()
    return final, session, bench


def test_lost_drive_is_reported_as_not_off_in_event_file_and_log(tmp_path):
    final, session, bench = _run_with(
        tmp_path, faults.LostConnection(instrument="drive", at_command=22))
    assert final.status == "failed"
    assert bench.world.drive.output  # the simulator's drive really is still on
    assert final.unsafe and all("drive" in m for m in final.unsafe), final.unsafe
    assert session.unsafe[: len(final.unsafe)] == final.unsafe
    with SessionReader(tmp_path / "s.h5") as reader:
        run = reader.handle["runs"]["000"].attrs
        assert not run["outputs_confirmed_off"]
        assert "OUTP OFF" in str(run["safe_state_errors"])
        last = [line for line in reader.log_lines() if "run failed" in line][-1]
        assert "OUTPUTS NOT CONFIRMED OFF" in last and "outputs off;" not in last


def test_run_that_switched_everything_off_says_so(tmp_path):
    final, session, bench = _run_with(
        tmp_path, faults.ScpiError(instrument="drive", at_command=22))
    assert final.status == "failed" and final.unsafe == () and session.unsafe == ()
    assert not bench.world.drive.output
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.handle["runs"]["000"].attrs["outputs_confirmed_off"]


def test_cli_exits_5_and_tells_the_operator(tmp_path, monkeypatch, capsys):
    from pelvislab.app.commands.run import EXIT_UNSAFE, run_command

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    real = runner_module.prepare_session

    def with_lost_drive(*args, **kwargs):
        kwargs["bench"] = _bench(faults.LostConnection(instrument="drive", at_command=22))
        return real(*args, **kwargs)

    monkeypatch.setattr(runner_module, "prepare_session", with_lost_drive)
    args = argparse.Namespace(protocol=str(protocol), out=str(tmp_path / "s.h5"), bench=None,
                              resume=False, wait_prompts=False, subject_id=None, quiet=True)
    assert run_command(args) == EXIT_UNSAFE
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "OUTPUTS NOT CONFIRMED OFF" in last and "by hand" in last
    assert "outputs off" not in last



def test_an_interrupt_inside_a_safe_state_is_not_an_output_left_on():
    # repeated Ctrl-C: the signal handler's interrupt raised inside Bench.safe_state (after
    # every instrument was handled) was reported as "OUTPUTS NOT CONFIRMED OFF"
    import threading

    from pelvislab.acquisition.runner import RunInterrupted, Runner

    class Bench:
        calls = 0

        def safe_state(self):
            Bench.calls += 1
            if Bench.calls == 1:
                raise RunInterrupted("interrupted by Ctrl-C (SIGINT)")
            return ["drive: OUTP OFF failed"] if Bench.calls == 2 else []

    runner = Runner.__new__(Runner)
    runner._lock, runner.bench, runner._unsafe = threading.RLock(), Bench(), []
    runner._safe_state()
    assert runner.unsafe == ()
    runner._safe_state()
    assert runner.unsafe == ("drive: OUTP OFF failed",)
    runner._safe_state()  # the last completed safe state decides
    assert runner.unsafe == ()


def test_disk_almost_full_stops_the_run_cleanly_before_a_write_fails(tmp_path, monkeypatch):
    # before: "No space left on device" inside an HDF5 write; the file could not be flushed
    # or closed, 140 lines of tracebacks, a segmentation fault at exit
    import shutil
    from collections import namedtuple

    usage = namedtuple("usage", "total used free")
    free = {"bytes": 10**12}
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(0, 0, free["bytes"]))
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    bench = sim_bench.open_simulated_bench(generators="python")
    with prepare_session(protocol, tmp_path / "s.h5", bench=bench) as session:
        def shrink(event):
            if type(event).__name__ == "StepFinished" and event.step.index == 1:
                free["bytes"] = 5 * 2**20  # the disk fills up while we measure
        session.runner.subscribe(shrink)
        final = session.run()
    assert final.status == "failed" and "disk almost full" in final.reason
    assert final.unsafe == () and not bench.world.drive.output
    with SessionReader(tmp_path / "s.h5") as reader:
        assert reader.status[0] == "failed"
        assert len(list(reader.steps())) == 2 and not reader.damaged
