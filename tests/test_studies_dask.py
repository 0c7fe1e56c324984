"""Study runs on a dask.distributed cluster (a LocalCluster in this process) equal the
local executor's results (runs are seeded)."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from pelvislab.model.studies import Run, dask_executor, run_all

distributed = pytest.importorskip("distributed")

RUNS = [Run("bins", "dp=0.1", seed=11, dp=0.1, df_hz=10.0, max_starts=1),
        Run("noise", "dp=0.2 noisy", seed=12, dp=0.2, df_hz=10.0, position_mm=2.0,
            orientation_deg=10.0, max_starts=1)]


def test_runs_on_a_local_dask_cluster_equal_the_local_executor() -> None:
    with ThreadPoolExecutor(1) as pool:
        local = run_all(RUNS, pool)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        with dask_executor(cluster.scheduler_address) as pool:
            remote = run_all(RUNS, pool)
    assert [o.run for o in remote] == RUNS
    for a, b in zip(local, remote, strict=True):
        assert a.identified == b.identified
        assert a.rel_error == b.rel_error
        assert a.rms_residual == b.rms_residual
    assert local[0].max_error < 1e-6  # noise-free run recovered
    assert local[1].rms_residual > 1e-4  # noisy run did see the noise


def test_unreachable_scheduler_is_a_one_line_error_within_the_timeout() -> None:
    t0 = time.perf_counter()
    with pytest.raises(ConnectionError, match="cannot reach the dask scheduler"):
        with dask_executor("tcp://127.0.0.1:9", connect_timeout_s=1.0):
            pass
    assert time.perf_counter() - t0 < 10
