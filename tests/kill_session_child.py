"""Child of test_session_durability: a short simulated run into ``argv[1]``.

With ``--mark``, ``step <i>`` goes to stderr when step ``i`` starts (a write(2) that a
strace of pwrite64 and write shows between the file's writes)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from pelvislab.acquisition.runner import prepare_session
from pelvislab.sim_instruments.bench import open_simulated_bench
from pelvislab.tests.test_runner_kill import PROTOCOL


def _mark(event: object) -> None:
    if type(event).__name__ == "StepStarted":
        os.write(2, f"step {event.step.index}\n".encode())  # type: ignore[attr-defined]


if __name__ == "__main__":
    out = Path(sys.argv[1])
    protocol = out.with_suffix(".toml")
    protocol.write_text(PROTOCOL)
    with prepare_session(protocol, out, bench=open_simulated_bench(generators="python")) as s:
        if "--mark" in sys.argv:
            s.runner.subscribe(_mark)
        s.run()
    os._exit(0)
