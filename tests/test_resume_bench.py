"""--resume refuses a bench whose calibration would make the new steps incomparable."""

from __future__ import annotations

import dataclasses

import pytest

from pelvislab.acquisition.runner import prepare_session
from pelvislab.drivers.bench import BenchConfig
from pelvislab.tests.test_runner_unsafe import PROTOCOL

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")


def _aborted_session(tmp_path):
    """(protocol, session file) of a run aborted before its first step."""
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    with prepare_session(protocol, out, bench=sim_bench.open_simulated_bench(
            generators="python")) as session:
        session.runner.abort("stopped for the test")
        session.run()
    return protocol, out


def test_resume_on_a_bench_with_another_calibration_is_refused(tmp_path):
    # before, the resumed steps of one setup mixed 0.1 N and 0.5 N forces at the same drive
    protocol, out = _aborted_session(tmp_path)
    other = dataclasses.replace(BenchConfig.default(), drive_newton_per_volt=5.0)
    with pytest.raises(ValueError, match="another bench.*drive_newton_per_volt"):
        prepare_session(protocol, out, resume=True,
                        bench=sim_bench.open_simulated_bench(other, generators="python"))
    with prepare_session(protocol, out, resume=True, bench=sim_bench.open_simulated_bench(
            generators="python")) as session:
        assert session.run().status == "completed"


def test_resume_says_how_the_last_run_ended(tmp_path, capsys):
    import argparse

    from pelvislab.acquisition.session import SessionReader
    from pelvislab.app.commands.run import run_command

    protocol, out = _aborted_session(tmp_path)
    with SessionReader(out) as reader:
        assert reader.status[0] == "aborted"
    args = argparse.Namespace(protocol=str(protocol), out=str(out), bench=None, resume=True,
                              wait_prompts=False, subject_id=None, quiet=True)
    assert run_command(args) == 0
    err = capsys.readouterr().err
    assert f"resuming {out}: its last run ended aborted (stopped for the test)" in err
    assert "did not end normally" not in err


def test_a_channel_speed_of_sound_added_or_removed_is_a_difference():
    # compared on the steps' echoes (what was used), no longer on /bench: a session written
    # before the bench's global value was applied recorded it there unused
    from types import SimpleNamespace

    from pelvislab.acquisition.runner import speed_of_sound_differences
    from pelvislab.acquisition.session import STATUS_COMPLETE

    protocol = SimpleNamespace(ultrasound=SimpleNamespace(speed_of_sound_m_s=1540.0))

    def steps(c):
        return [SimpleNamespace(status=STATUS_COMPLETE,
                                channels=[SimpleNamespace(name="ch1", speed_of_sound_m_s=c)])]

    plain = BenchConfig.default()
    with_ch1 = dataclasses.replace(plain, channel_speed_of_sound_m_s={1: 1480.0})
    assert speed_of_sound_differences(steps(1540.0), with_ch1, protocol)
    assert speed_of_sound_differences(steps(1480.0), plain, protocol)
    same_as_protocol = dataclasses.replace(plain, channel_speed_of_sound_m_s={1: 1540.0})
    assert speed_of_sound_differences(steps(1540.0), same_as_protocol, protocol) == []


def test_resuming_a_finished_session_opens_and_writes_nothing(tmp_path, capsys):
    # it said "0 steps to go", exit 0, but opened the bench and wrote a run record into
    # the finished file (first-day review, session 39)
    import argparse
    import hashlib

    from pelvislab.acquisition.runner import NothingToResume
    from pelvislab.app.commands.run import run_command

    protocol, out = _aborted_session(tmp_path)
    with prepare_session(protocol, out, resume=True, bench=sim_bench.open_simulated_bench(
            generators="python")) as session:
        assert session.run().status == "completed"
    before = hashlib.sha256(out.read_bytes()).hexdigest()
    with pytest.raises(NothingToResume, match="already holds every step"):
        prepare_session(protocol, out, resume=True, bench=None)
    args = argparse.Namespace(protocol=str(protocol), out=str(out), bench=None, resume=True,
                              wait_prompts=False, subject_id=None, quiet=True)
    assert run_command(args) == 0
    assert "nothing to measure; the file is left as it is" in capsys.readouterr().err
    assert hashlib.sha256(out.read_bytes()).hexdigest() == before


def test_an_output_that_is_a_folder_is_named_as_such(tmp_path, capsys):
    # "exists; not overwriting it (use --resume ...)" sent the user the wrong way
    # (first-day review, session 39)
    from pelvislab.app.cli import main

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    for extra in ([], ["--resume"]):
        assert main(["run", str(protocol), "--out", str(tmp_path), *extra]) == 1
        err = capsys.readouterr().err
        assert f"{tmp_path} is a folder: give the session file's name" in err, err
