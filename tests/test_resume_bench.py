"""--resume refuses a bench whose calibration would make the new steps incomparable."""

from __future__ import annotations

import dataclasses

import pytest

from pelvislab.acquisition.runner import prepare_session
from pelvislab.drivers.bench import BenchConfig
from pelvislab.tests.test_runner_unsafe import PROTOCOL

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")


def test_resume_on_a_bench_with_another_calibration_is_refused(tmp_path):
    # before, the resumed steps of one setup mixed 0.1 N and 0.5 N forces at the same drive
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    with prepare_session(protocol, out, bench=sim_bench.open_simulated_bench(
            generators="python")) as session:
        session.runner.abort("stopped for the test")
        session.run()
    other = dataclasses.replace(BenchConfig.default(), drive_newton_per_volt=5.0)
    with pytest.raises(ValueError, match="another bench.*drive_newton_per_volt"):
        prepare_session(protocol, out, resume=True,
                        bench=sim_bench.open_simulated_bench(other, generators="python"))
    with prepare_session(protocol, out, resume=True, bench=sim_bench.open_simulated_bench(
            generators="python")) as session:
        assert session.run().status == "completed"
