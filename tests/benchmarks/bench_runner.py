"""Runner and sessions: demo run time vs bench time, session write rate, kill -9 survival."""

from __future__ import annotations

import random
import tempfile
import time
from importlib import resources
from pathlib import Path

from pelvislab.tests.benchmarks.harness import Result

N_KILLS = 40


def _demo_run(folder: Path) -> tuple[float, float, int, float]:
    """(wall s, bench-time estimate s, steps, session MB) of protocols/demo.toml on the
    fast-paced simulated bench, in this process."""
    from pelvislab.acquisition.protocol import load_protocol
    from pelvislab.acquisition.runner import prepare_session
    from pelvislab.sim_instruments.bench import open_simulated_bench

    path = Path(str(resources.files("pelvislab.protocols") / "demo.toml"))
    estimate = load_protocol(path).estimated_duration_s()
    out = folder / "demo.h5"
    started = time.perf_counter()
    with prepare_session(path, out, bench=open_simulated_bench()) as session:
        final = session.run()
    wall = time.perf_counter() - started
    return wall, estimate, final.n_done, out.stat().st_size / 1e6


def _kill_survival(folder: Path) -> tuple[int, int, int, int]:
    """(files created, files consistent, resumes tried, resumes completed) over N_KILLS
    SIGKILLs at random moments (tests/test_runner_kill.py helpers)."""
    from pelvislab.tests import test_runner_kill as tk

    protocol = folder / "p.toml"
    protocol.write_text(tk.PROTOCOL)
    warm = folder / "warm.h5"
    bench = tk.sim_bench.open_simulated_bench(generators="python")
    with tk.prepare_session(protocol, warm, bench=bench) as session:
        session.run()
    _, duration = tk._run(protocol, folder / "full.h5")
    rng = random.Random(1)
    created = consistent = tried = resumed = 0
    for k in range(N_KILLS):
        out = folder / f"k{k}.h5"
        tk._run(protocol, out, kill_after_s=rng.uniform(0.0, 1.1 * duration))
        if not out.exists():
            continue
        created += 1
        try:
            n = tk.check_consistent(out)
        except Exception:  # counted as not consistent
            continue
        consistent += 1
        if n < tk.N_STEPS and k % 3 == 0:
            tried += 1
            with tk.SessionReader(out) as reader:
                interrupted = set(reader.step_names()[-1:])
            code, _ = tk._run(protocol, out, resume=True)
            try:
                if code == 0 and tk.check_consistent(out, interrupted) == tk.N_STEPS:
                    resumed += 1
            except Exception:
                pass
    return created, consistent, tried, resumed


def run() -> list[Result]:
    """Figures of the runner (measured on this machine, fast-paced simulated bench)."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        wall, estimate, steps, mb = _demo_run(folder)
        created, consistent, tried, resumed = _kill_survival(folder)
    return [
        Result(f"demo protocol run ({steps} steps, fast sim): wall time", wall, "s",
               baseline=estimate, baseline_name="real-bench settle+record time",
               target="< 120 s (make demo, issue 7)"),
        Result("demo protocol run: time per step", wall / max(steps, 1) * 1e3, "ms"),
        Result("demo session file size", mb, "MB"),
        Result(f"kill -9 at {N_KILLS} random moments: files that open and are consistent",
               100.0 * consistent / max(created, 1), "%", target="100 %"),
        Result("resumed killed sessions that complete the plan",
               100.0 * resumed / max(tried, 1), "%", target="100 %"),
    ]
