"""Nothing lost: kill -9 at random moments of runs on the simulated bench; SIGINT via the CLI.

Each killed run is a forked child process (the imports are already loaded, so many kills
stay fast) running the real runner + session writer on the fast-paced simulated bench; the
parent SIGKILLs it at a random moment. Afterwards every file must open, every step marked
complete must read back whole, /frf must hold only lines of complete steps, and resuming
must finish the plan with no step lost or repeated.
"""

from __future__ import annotations

import multiprocessing
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pelvislab.acquisition.frfset import read_frf
from pelvislab.acquisition.session import SessionFileError, SessionReader

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")
from pelvislab.acquisition.runner import prepare_session  # noqa: E402

PROTOCOL = """
schema = "pelvislab-protocol"
schema_version = 1
name = "kill-test"
[sweep]
frequencies_hz = [60.0, 120.0, 180.0, 240.0]
drive_vpp = 0.2
settle_s = 0.05
[ultrasound]
pulses = 250
samples = 500
[[setups]]
name = "a"
excitation = "SIAS_R_x"
transducers = { ch1 = "SIAS_R_x", ch2 = "sacrum_x" }
[[setups]]
name = "b"
excitation = "SIAS_R_x"
transducers = { ch1 = "SIPS_R_x", ch2 = "SIPS_L_x" }
"""
N_STEPS = 8
N_KILLS = 20  # issue 7: "kill -9 at 20 random moments"


def _child(protocol: str, out: str, resume: bool) -> None:
    bench = sim_bench.open_simulated_bench(generators="python")
    with prepare_session(protocol, out, bench=bench, resume=resume) as session:
        session.run()
    os._exit(0)


def _run(protocol: Path, out: Path, resume: bool = False,
         kill_after_s: float | None = None) -> tuple[int, float]:
    ctx = multiprocessing.get_context("fork")
    proc = ctx.Process(target=_child, args=(str(protocol), str(out), resume))
    started = time.monotonic()
    proc.start()
    if kill_after_s is not None:
        proc.join(kill_after_s)
        if proc.is_alive():
            os.kill(proc.pid, signal.SIGKILL)
    proc.join(60)
    return proc.exitcode, time.monotonic() - started


def _cli_run(tmp_path: Path, *options: str, **popen: object) -> tuple[subprocess.Popen, Path]:
    """``pelvislab run`` of :data:`PROTOCOL` into ``tmp_path/s.h5`` in a child process
    (``options`` after ``--out``; ``popen`` to :class:`subprocess.Popen`)."""
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    return subprocess.Popen([sys.executable, "-m", "pelvislab.app", "run", str(protocol),
                             "--out", str(out), *options], **popen), out


def check_consistent(path: Path, interrupted: set[str] | frozenset[str] = frozenset()) -> int:
    """Every complete step whole, /frf lines only from complete steps; returns #complete.
    ``interrupted``: step groups a kill interrupted before this file was resumed."""
    with SessionReader(path) as reader:  # must open: no SessionFileError
        steps = list(reader.steps())
        keys = [s.key for s in steps]
        assert len(keys) == len(set(keys))
        for s in steps:
            assert len(s.channels) == 2
            for c in s.channels:
                assert c.codes.shape == (250, 500) and c.codes.dtype == np.int8
                assert c.trigger_offset_s.shape == (250,)
                assert c.displacement_m is not None and c.displacement_m.shape == (250,)
                assert c.phasor_m is not None and np.isfinite(c.phasor_m)
        if steps:  # the instruments' audit trail is stored with every step, not at the end
            # (in the run that measured them: after a resume, not necessarily run 000)
            runs = reader.handle["runs"]
            texts = [bytes(t) for name in runs
                     if "drive" in runs[name].get("command_logs", {})
                     for t in runs[name]["command_logs/drive/text"][()]]
            assert b"OUTP ON" in texts, texts[-5:]
        # only the step being flushed when the kill came may be unreadable: the last group,
        # or after --resume the group an earlier kill interrupted (the resumed run redoes
        # that step in a new group and leaves the damaged one listed, never read)
        names = reader.step_names()
        may_be_damaged = {*names[-1:], *interrupted}
        assert all(d.split(":")[0] in may_be_damaged for d in reader.damaged), reader.damaged
    frf = read_frf(path)
    measured = {(round(f, 6), o, j) for f, o, j in zip(*[
        v.tolist() for v in np.nonzero(np.isfinite(frf.H))], strict=True)}
    expected = set()
    for s in steps:
        i = int(np.argmin(abs(frf.frequency_hz - s.frequency_hz)))
        j = frf.inputs.index(s.input.name)
        for c in s.channels:
            if c.quality.get("ok", True):
                expected.add((i, frf.outputs.index(c.output.name), j))
                stored = frf.H[i, frf.outputs.index(c.output.name), j]
                if np.isfinite(stored):  # else: killed between the step and its /frf line
                    assert stored == pytest.approx(c.phasor_m / s.force_phasor_n)
    got = {(int(f), o, j) for f, o, j in measured}
    # /frf lines are written after their step is flushed: a kill in between may leave the
    # last step's lines unwritten (resume rewrites them), never a line without its step
    assert got <= expected and len(expected - got) <= 2, (got, expected)
    return len(steps)


def test_kill_minus_9_at_random_moments_loses_nothing(tmp_path):
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    warm = tmp_path / "warm.h5"  # in this process: loads and caches what every child needs
    with prepare_session(protocol, warm,
                         bench=sim_bench.open_simulated_bench(generators="python")) as session:
        assert session.run().status == "completed"
    full = tmp_path / "full.h5"
    code, duration = _run(protocol, full)
    assert code == 0
    assert check_consistent(full) == N_STEPS
    rng = random.Random(20261122)
    outcomes = []
    for k in range(N_KILLS):
        out = tmp_path / f"k{k}.h5"
        _run(protocol, out, kill_after_s=rng.uniform(0.0, 1.1 * duration))
        if not out.exists():
            outcomes.append(-1)  # killed before the file was created: nothing to lose
            continue
        outcomes.append(check_consistent(out))
    assert sum(0 < n < N_STEPS for n in outcomes) >= 3, outcomes  # kills did land mid-run
    # resume a few interrupted sessions: the plan completes, nothing lost or repeated
    for k in [k for k, n in enumerate(outcomes) if 0 <= n < N_STEPS][:2]:
        out = tmp_path / f"k{k}.h5"
        before = outcomes[k]
        with SessionReader(out) as reader:
            interrupted = set(reader.step_names()[-1:])
        code, _ = _run(protocol, out, resume=True)
        assert code == 0
        assert check_consistent(out, interrupted) == N_STEPS
        with SessionReader(out) as reader:
            assert len(reader.step_names()) >= N_STEPS
            assert reader.status[0] == "completed"
            assert before <= N_STEPS


def test_ctrl_c_via_cli_outputs_off_within_100_ms(tmp_path):
    protocol = tmp_path / "p.toml"
    many = ", ".join(f"{f:.1f}" for f in range(40, 240, 10))  # 2 x 20 steps: seconds
    protocol.write_text(PROTOCOL.replace("pulses = 250", "pulses = 2000").replace(
        "60.0, 120.0, 180.0, 240.0", many))
    out = tmp_path / "s.h5"
    proc = subprocess.Popen([sys.executable, "-m", "pelvislab.app", "run", str(protocol),
                             "--out", str(out)], stderr=subprocess.PIPE, text=True)
    first = proc.stderr.readline()  # "run ...: N steps to go" once the run has started
    assert first.startswith("run "), first
    time.sleep(0.5)
    t_sigint = time.monotonic()
    proc.send_signal(signal.SIGINT)
    rest = proc.stderr.read()
    code = proc.wait(30)
    assert code == 130
    final = [ln for ln in rest.splitlines() if ln.startswith("pelvislab run:")]
    assert len(final) == 1 and "interrupted" in final[0] and "Traceback" not in rest
    assert "of 40 steps" in final[0]
    # said once: the run's closing log line is not echoed as an "error:" line before it
    assert "error: run interrupted" not in rest, rest
    with SessionReader(out) as reader:
        assert reader.status[0] == "interrupted"
        logs = reader.handle["runs/000/command_logs"]
        for role in ("drive", "trigger"):
            times = logs[role]["time_s"][()]
            texts = [t.decode() if isinstance(t, bytes) else t for t in logs[role]["text"][()]]
            off = [t for t, s in zip(times, texts, strict=True)
                   if s.strip().upper() in ("OUTP OFF", "OUTP 0") and t >= t_sigint]
            assert off and off[0] - t_sigint < 0.1, (role, texts[-5:])


def test_interrupt_inside_exec_code_still_exits_130(tmp_path):
    """The signal handler's exception can land in code run by exec() of a string (a lazy
    import defining a dataclass); CPython 3.11 then exits by SIGINT (status -2, not 130) at
    the end of ``python -m`` if that exception is exactly KeyboardInterrupt, even though the
    runner caught it. CI saw this; the runner raises a subclass instead."""
    (tmp_path / "interrupt_in_exec.py").write_text(
        "import sys\n"
        "from pelvislab.acquisition.runner import RunInterrupted\n"
        "try:\n"
        "    exec('raise RunInterrupted(\"x\")')\n"
        "except KeyboardInterrupt:\n"
        "    pass\n"
        "sys.exit(130)\n")
    proc = subprocess.run([sys.executable, "-m", "interrupt_in_exec"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 130, proc.stderr


def test_truncated_session_is_refused_cleanly(tmp_path):
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    assert _run(protocol, out)[0] == 0
    data = out.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 3])
    # not "in use by another process": "sblock" is no lock; how far short it is, and what
    # extends it (session 50: a write that failed part way leaves such a file)
    with pytest.raises(SessionFileError, match="ends [0-9]+ bytes before the end"):
        SessionReader(cut)


def test_wait_prompts_answered_then_stdin_closed_aborts(tmp_path):
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    proc = subprocess.run([sys.executable, "-m", "pelvislab.app", "run", str(protocol),
                           "--out", str(out), "--wait-prompts"],
                          input="\n", capture_output=True, text=True, timeout=120)
    assert proc.returncode == 4, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("pelvislab run: aborted: operator prompt") and "4 of 8" in last
    assert "Traceback" not in proc.stderr
    with SessionReader(out) as reader:
        assert [s.setup for s in reader.steps()] == ["a"] * 4  # setup a confirmed and kept
        assert reader.status[0] == "aborted"


def test_sigterm_while_waiting_at_the_operator_prompt_ends_the_run(tmp_path):
    # before: the prompt's read of stdin blocked inside a runner listener, so Ctrl-C or
    # SIGTERM left the run waiting (outputs off, but no end) until Enter or end of input
    proc, out = _cli_run(tmp_path, "--wait-prompts", stdin=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        line = ""
        while "PROMPT" not in line:
            line = proc.stderr.readline()
            assert line, "no prompt before the end of the output"
        proc.send_signal(signal.SIGTERM)  # stdin stays open: nobody answers
        code = proc.wait(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdin.close()
    assert code == 130
    with SessionReader(out) as reader:
        assert reader.status[0] == "interrupted"


def test_completed_run_exits_0_when_nobody_reads_stderr_any_more(tmp_path):
    # pelvislab run ... 2>&1 | head -1: a complete session exited 1 (BrokenPipeError on
    # the last line, turned into "error")
    proc, out = _cli_run(tmp_path, stderr=subprocess.PIPE)
    proc.stderr.readline()
    proc.stderr.close()
    assert proc.wait(timeout=120) == 0
    with SessionReader(out) as reader:
        assert reader.status[0] == "completed"


def _eta_run(tmp_path):
    """The ETA tests' protocol file, its planned step durations (s) and a simulated bench."""
    from pelvislab.acquisition.protocol import load_protocol

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    loaded = load_protocol(protocol)
    estimate = [loaded.step_duration_s(s.frequency_hz) for s in loaded.steps()]
    return protocol, estimate, sim_bench.open_simulated_bench(generators="python")


def test_eta_leaves_out_the_time_at_an_operator_prompt(tmp_path):
    # before: a prompt answered after 6 s made the ETA jump from 15 to 32 s
    protocol, estimate, bench = _eta_run(tmp_path)
    rates = {}
    with prepare_session(protocol, tmp_path / "s.h5", bench=bench,
                         auto_continue=False) as session:
        runner = session.runner

        def listen(event):
            name = type(event).__name__
            if name == "OperatorPrompt":
                delay = 0.0 if event.setup_index == 0 else 3.0
                threading.Timer(delay, runner.confirm).start()
            elif name == "Progress" and event.n_done in (4, 5):
                left = sum(estimate[event.n_done:])
                rates[event.n_done] = event.eta_s / left  # measured s per planned s
        runner.subscribe(listen)
        assert session.run().status == "completed"
    # the same pace before and after the 3 s wait (the ETA scales the planned time left):
    # counted, the wait would make the rate at step 5 at least 3 s over the 4 planned steps
    # since the first (~7.5, against ~0.2-0.4 either side of it); checked against that,
    # not as a ratio of the two one-step-scale rates, which varies ~2x under load (the
    # same form failed in session 47's clean-clone run in the test below)
    wait_counted = 3.0 / sum(estimate[1:5])
    assert rates[4] < wait_counted / 4 and rates[5] < wait_counted / 4, rates


def test_eta_leaves_out_the_first_steps_one_off_start(tmp_path):
    # helper review, session 34: a resumed run's first ETA read 103 s for ~5 s of work; the
    # first step carries the start (bench, digitizer set-up), here made 3 s long
    protocol, estimate, bench = _eta_run(tmp_path)
    rates = {}
    with prepare_session(protocol, tmp_path / "s.h5", bench=bench) as session:
        def listen(event):
            name = type(event).__name__
            if name == "StepStarted" and event.n_done == 0:
                time.sleep(3.0)
            elif name == "Progress" and event.n_done in (2, 6):
                rates[event.n_done] = event.eta_s / sum(estimate[event.n_done:])
        session.runner.subscribe(listen)
        assert session.run().status == "completed"
    # counted as pace, the 3 s start would make the rate at step 2 at least 3 s over the
    # first two steps' planned time (~15, and ~5 at step 6) against ~0.2-0.4 here; a ratio
    # of the two rates, as first written, failed under load when the one step the pace
    # then rests on ran slow (a clean-clone run, session 47: 0.357 against 0.217 > 1.6x)
    start_counted = 3.0 / sum(estimate[:2])
    assert rates[2] < start_counted / 5 and rates[6] < start_counted / 5, rates
