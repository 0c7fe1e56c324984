"""Study runs (ch. 6.2 / 7 on the appendix E model): one small seeded run each path."""

from __future__ import annotations

import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

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


@pytest.mark.gui
def test_plots_are_drawn_from_the_committed_summaries(tmp_path: Path) -> None:
    import importlib.util

    import pyqtgraph as pg
    from PySide6.QtGui import QColor, QImage

    studies_dir = Path(__file__).resolve().parents[1] / "docs" / "studies"
    for name in ("ch6_summary.csv", "ch7_summary.csv"):
        shutil.copy(studies_dir / name, tmp_path / name)
    spec = importlib.util.spec_from_file_location("plot_studies",
                                                  studies_dir / "plot_studies.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    background = pg.getConfigOption("background")
    assert module.main(["--dir", str(tmp_path)]) == 0
    assert pg.getConfigOption("background") == background  # global look restored
    blue = QColor(*module.COLOURS["ours"]).rgb()
    for name, width in (("ch6_success_mass.png", 1400), ("ch6_stiffness.png", 1800),
                        ("ch7_errors.png", 1800)):
        image = QImage(str(tmp_path / name))
        assert image.width() == width and image.height() > 300
        # our curves were drawn (not an empty scene): some pixels carry their colour
        step = 3
        hits = sum(image.pixel(x, y) == blue for x in range(0, image.width(), step)
                   for y in range(0, image.height(), step))
        assert hits > 20, name
