"""Child of test_session_durability: a short simulated run into ``argv[1]``."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from pelvislab.acquisition.runner import prepare_session
from pelvislab.sim_instruments.bench import open_simulated_bench
from pelvislab.tests.test_runner_kill import PROTOCOL

if __name__ == "__main__":
    out = Path(sys.argv[1])
    protocol = out.with_suffix(".toml")
    protocol.write_text(PROTOCOL)
    with prepare_session(protocol, out, bench=open_simulated_bench(generators="python")) as s:
        s.run()
    os._exit(0)
