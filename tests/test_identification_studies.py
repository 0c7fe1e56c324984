"""Study runs (ch. 6.2 / 7 on the appendix E model): one small seeded run each path."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from pelvislab.model.studies import (
    Run,
    ch7_runs,
    execute,
    markdown_table,
    run_all,
    summarise_ch6,
    summarise_ch7,
)


def test_noise_free_run_recovers_all_parameters_through_an_executor() -> None:
    runs = [Run("bins", "dp=0.3", seed=3, dp=0.3, df_hz=5.0)]
    with ThreadPoolExecutor(1) as pool:
        (out,) = run_all(runs, pool)
    assert out.max_error < 1e-6
    assert len(out.names) == 18
    rows = summarise_ch6([out])
    assert rows[0]["success_pct"] == 100.0
    assert "| study |" in markdown_table(rows)


def test_noise_is_seeded_and_degrades_the_fit() -> None:
    run = Run("noise", "x", seed=5, dp=0.1, df_hz=10.0, position_mm=2.0, orientation_deg=10.0,
              max_starts=1)
    a, b = execute(run), execute(run)
    assert a.identified == b.identified
    assert a.rms_residual > 1e-4  # the model cannot explain displaced sensors exactly


def test_ch7_version_b_case_reports_modal_errors() -> None:
    run = next(r for r in ch7_runs() if r.version_b and r.f_k == 0.5 and r.f_c == 0.0)
    out = execute(run)
    row = summarise_ch7([out])[0]
    assert row["recovered"] and row["version"] == "B"
    assert abs(row["f_k_identified"] - 0.5) < 1e-6
    assert row["mac_min"] > 0.999
    assert np.nanmax(np.abs(out.extra["frequency_error_pct"])) < 1e-6
