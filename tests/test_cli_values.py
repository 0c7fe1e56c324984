"""Option values that mean nothing are refused with one line before any work."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from pelvislab.acquisition.frfset import Channels, FrfFileError, FrfSet, read_frf, write_frf
from pelvislab.app.cli import main


@pytest.mark.parametrize(("argv", "message"), [
    (["model", "modes", "--f-k", "-5"], "--f-k -5.0: must be between -4 and 100"),
    (["model", "modes", "--f-c", "-1"], "--f-c -1.0: must be between 0 and 100"),
    (["model", "frf", "--points", "sacrum_x", "--step-hz", "nan"], "finite"),
    (["model", "frf", "--points", "sacrum_x", "--step-hz", "1e-9"], "a million"),
    (["ema", "S.h5", "--json", "e.json", "--frequencies", "-5"], "positive frequencies"),
    (["ema", "S.h5", "--json", "e.json", "--frequencies", "nan"], "positive frequencies"),
    (["identify", "S.h5", "--json", "i.json", "--starts", "0"], "--starts 0"),
    (["identify", "S.h5", "--json", "i.json", "--params", ","], "got none"),
    (["identify", "S.h5", "--json", "i.json", "--params", "k_io_R,k_pubh,k_io_R"],
     "k_io_R named more than once"),
    (["identify", "S.h5", "--json", "i.json", "--profile", "k_pubh, k_pubh"],
     "k_pubh named more than once"),
    (["gap", "diagnose", "S.h5", "--json", "g.json", "--effects", "added_mass,added_mass"],
     "added_mass named more than once"),
    (["identify", "S.h5", "--json", ""], "the output's name is empty"),
    (["ema", "S.h5", "--json", "e.json", "--update", ""], "got none"),
    (["gap", "diagnose", "S.h5", "--json", " "], "the output's name is empty"),
    (["gap", "diagnose", "S.h5", "--json", "g.json", "--effects", ","], "got none"),
    (["gap", "benchmark", "--json", "b.json", "--kinds", "none,nope"], "unknown nope"),
])
def test_meaningless_values_are_refused(argv, message, tmp_path, monkeypatch, capsys):
    # before: a parameter named twice in --params fitted as two (each std n/a,
    # "converged"), an empty --json read as the folder ".", --update "" run as no
    # update (exit 0), an argmax of an empty
    # sequence, negative damping ratios, NaN-to-integer,
    # a 2 TiB allocation, a pole picked for -5 Hz, "--starts 0" run as 1 start, "," read
    # as "every parameter", min() of an empty sequence, a file named "-", a benchmark
    # whose unknown kind was found only at the end
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_frf_in_other_units_is_refused(tmp_path):
    point = Channels(["p"], ["sacrum"], np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]))
    frf = FrfSet(np.array([10.0, 20.0]), np.ones((2, 1, 1), complex), point, point)
    path = tmp_path / "f.h5"
    with h5py.File(path, "w") as f:
        write_frf(f, frf)
        f["frf"].attrs["units"] = "m/s/N"  # a mobility
    with pytest.raises(FrfFileError, match="units 'm/s/N'.*receptance in m/N"):
        read_frf(path)


def test_analysis_of_an_interrupted_session_warns(tmp_path, capsys):
    # before: ema on 148 of 308 steps (one excitation missing entirely) said nothing
    from pelvislab.acquisition.runner import prepare_session
    from pelvislab.sim_instruments.bench import open_simulated_bench
    from pelvislab.tests.test_runner_kill import PROTOCOL

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    with prepare_session(protocol, out, bench=open_simulated_bench(generators="python")) as s:
        def stop_after_four(event):
            if type(event).__name__ == "StepFinished" and event.step.index == 3:
                s.runner.abort("stopped for the test")
        s.runner.subscribe(stop_after_four)
        s.run()
    main(["export-uff", str(out), str(tmp_path / "o.uff")])
    err = capsys.readouterr().err
    assert "its last run ended 'aborted', not completed" in err
    assert "2 of the 4 planned FRFs hold data" in err  # setup b never ran


def test_verbose_may_follow_the_command(tmp_path, capsys):
    # docs/identification.md writes "pelvislab identify S.h5 --json OUT -v"; argparse
    # refused it ("unrecognized arguments: -v", exit 2)
    code = main(["identify", str(tmp_path / "missing.h5"), "--json", str(tmp_path / "o.json"),
                 "-v"])
    assert code == 1 and "no such file" in capsys.readouterr().err


def test_gap_benchmark_makes_no_folder_for_options_it_refuses(tmp_path, capsys):
    out = tmp_path / "new_folder" / "b.json"
    assert main(["gap", "benchmark", "--json", str(out), "--kinds", "nope"]) == 1
    assert not out.parent.exists()


def test_a_real_bench_waits_for_the_operator_at_prompts_by_default(tmp_path, capsys):
    # first-day review, session 36: `run --bench` on a real bench auto-continued, so the
    # shaker drove on at once and every setup's data went under landmarks nobody had
    # placed a transducer on
    import argparse

    from pelvislab.app.commands.run import wait_for_operator
    from pelvislab.tests.test_drivers_bench import GOOD

    real = tmp_path / "lab.toml"
    real.write_text(GOOD)
    sim = tmp_path / "sim.toml"
    sim.write_text(GOOD.replace('name = "lab 3"', 'name = "dry"\nsimulated = true'))

    def args(bench, wait=False, auto=False):
        return argparse.Namespace(bench=bench, wait_prompts=wait, auto_continue=auto)

    assert wait_for_operator(args(str(real))) is True
    assert wait_for_operator(args(str(real), auto=True)) is False
    assert wait_for_operator(args(None)) is False
    assert wait_for_operator(args(str(sim))) is False
    assert wait_for_operator(args(None, wait=True)) is True
    # the two options exclude each other
    with pytest.raises(SystemExit) as stop:
        main(["run", "protocols/demo.toml", "--out", str(tmp_path / "s.h5"),
              "--wait-prompts", "--auto-continue"])
    assert stop.value.code == 2 and "not allowed with argument" in capsys.readouterr().err


def test_run_waits_at_prompts_when_wait_for_operator_says_so(tmp_path, monkeypatch, capsys):
    # review of the latest commits: only the helper was tested, not that run uses it
    import io
    import sys

    from pelvislab.app.commands import run as run_cmd

    monkeypatch.setattr(run_cmd, "wait_for_operator", lambda args: True)
    monkeypatch.setattr(sys, "stdin", io.StringIO(""))  # nobody to press Enter
    out = tmp_path / "s.h5"
    assert main(["run", "protocols/demo.toml", "--out", str(out)]) == 4
    err = capsys.readouterr().err
    assert "operator prompt: no answer (stdin closed)" in err
    assert "--auto-continue" not in err  # a hint for real benches only


def test_a_completed_run_that_lost_lines_says_so_in_its_last_line(tmp_path, capsys):
    # audit, session 41: nine_point at a fixed 0.5 Vpp lost its 10 Hz line in every setup
    # and ended "session complete: 275 of 275 steps", exit 0, the quality warnings long
    # scrolled past. The demo's first setup at 10 Hz moves one of its points out of the
    # record.
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "protocols" / "demo.toml").read_text()
    text = re.sub(r"frequencies_hz = \[.*?\]", "frequencies_hz = [10, 60]", text,
                  flags=re.DOTALL)
    first_two = [m.start() for m in re.finditer(r"^\[\[setups\]\]", text, re.MULTILINE)][:2]
    protocol = tmp_path / "p.toml"
    protocol.write_text(text[:first_two[1]])
    out = tmp_path / "s.h5"
    assert main(["run", str(protocol), "--out", str(out), "--quiet"]) == 0
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("session complete: 2 of 2 steps"), last
    assert last.endswith("1 of 4 FRF values missing (steps whose channels failed quality: "
                         "see the warnings above), at 10 Hz"), last


def test_the_missing_values_count_planned_pairs_that_lost_every_line(tmp_path):
    # review, session 41: a pair whose channel failed at every step added nothing, and a
    # run missing 78 of 616 planned values said "1 of 539"
    import shutil
    from pathlib import Path

    from pelvislab.acquisition.protocol import load_protocol
    from pelvislab.app.commands.run import _missing_frf_values
    from pelvislab.tests.test_identify_estimated_noise import DATA

    protocol = load_protocol(Path(__file__).resolve().parents[1] / "protocols" / "demo.toml")
    copy = tmp_path / "s.h5"
    shutil.copy(DATA, copy)
    assert _missing_frf_values(str(copy), protocol) == ""
    with h5py.File(copy, "a") as handle:
        H = handle["frf/H"][()]
        H[:, 1, 0] = np.nan
        H[3, 2, 1] = np.nan
        handle["frf/H"][...] = H
    said = _missing_frf_values(str(copy), protocol)
    assert said.startswith("; 78 of 616 FRF values missing"), said
