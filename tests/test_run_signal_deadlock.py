"""A signal during a run: the outputs are put off by the CLI's watcher thread, never by the
handler in the run's own thread.

CPython runs the handler between any two bytecodes of the run, also inside an instrument's
or the simulator's lock. Putting the outputs off from there deadlocked against the watcher
thread doing the same (it held a pulser's lock and waited for the simulator's, the handler
the other way round): `test_ctrl_c_via_cli_outputs_off_within_100_ms` hung in 2 of 4 full
runs under load, the child ignoring every further SIGINT and SIGTERM.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from pelvislab.acquisition.runner import prepare_session
from pelvislab.tests.test_runner_kill import PROTOCOL

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")


def test_a_signal_inside_the_simulators_lock_leaves_the_safe_state_to_the_watcher(
        tmp_path, monkeypatch):
    from pelvislab.app.commands.run import _run_with_signals
    from pelvislab.drivers.bench import Bench
    from pelvislab.sim_instruments.world import World

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers can only be installed in the main thread")
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    # the python pulsers: with the serial-port simulator the old code deadlocked for good
    bench = sim_bench.open_simulated_bench(generators="python", pulsers="python")
    calls: list[tuple[str, bool]] = []
    safe_state = Bench.safe_state

    def recorded_safe_state(self):
        calls.append((threading.current_thread().name, bench.world._lock._is_owned()))
        return safe_state(self)

    synthesize = World._synthesize

    def interrupted_synthesize(self, *args, **kwargs):
        if len(self.truth) == 1:  # the second record: a run under way, in the world's lock
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)  # the Python-level handler runs here
        return synthesize(self, *args, **kwargs)

    monkeypatch.setattr(Bench, "safe_state", recorded_safe_state)
    monkeypatch.setattr(World, "_synthesize", interrupted_synthesize)
    with prepare_session(protocol, tmp_path / "s.h5", bench=bench) as prepared:
        final = _run_with_signals(prepared)
    assert final.status == "interrupted" and final.n_done == 1
    assert calls, "no safe state at all"
    assert not [name for name, in_lock in calls if in_lock], calls
    assert "pelvislab-signals" in {name for name, _ in calls}
