"""Numbers of the gap JSON (design 4.4) that readers take at face value (contract audit).

``shrink = 1 - gap_after/gap_before`` is undefined when ``gap_before`` is 0. Design 4.4 fixes
a float: 0.0 (null in sessions 40-49, a contract change without a schema bump that a docs
review found in session 50), and every reader says n/a from ``gap_before`` rather than
showing a 0 % shrink. ``tests/data/demo_sim_seed1.h5``
(a simulated-chain session's /frf, no effect) has gap_before 0, like ``make demo``'s.

The ``where`` shares sum to 1 (design 4.4) to 1e-9 in each list: rounded to 4 digits they
summed to 0.99993-1.00002.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from pelvislab.acquisition.frfset import Channels
from pelvislab.app.cli import main

DATA = Path(__file__).parent / "data" / "demo_sim_seed1.h5"


def _strict(text: str) -> dict:
    """JSON with NaN/Infinity refused (they are not JSON)."""
    def refuse(token: str) -> None:
        raise ValueError(f"{token} in the JSON")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def demo_gap(tmp_path_factory) -> tuple[int, str, str, dict]:
    """``gap diagnose`` of the demo file (one effect keeps it short: ~10 s)."""
    out = tmp_path_factory.mktemp("gap") / "g.json"
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(["gap", "diagnose", str(DATA), "--json", str(out), "--no-plots",
                     "--effects", "added_mass,sensor_misorientation", "--jobs", "2"])
    return code, stdout.getvalue(), stderr.getvalue(), _strict(out.read_text())


def test_shrink_at_gap_before_0_is_a_float_and_every_reader_says_n_a(demo_gap, qtbot):
    code, stdout, stderr, doc = demo_gap
    assert code == 0, stderr
    assert doc["gap_before"] == 0.0 and doc["candidates"]
    assert all(type(c["shrink"]) is float and c["shrink"] == 0.0 for c in doc["candidates"])
    # the text report: no "0%" shrink, and why
    rows = [line for line in stdout.splitlines() if " shrink " in line and " @ " in line]
    assert rows and all("shrink    n/a" in line for line in rows)
    assert "no shrink can be measured" in stdout
    # the GUI's gap pane: a dash in the table, the reason in the summary
    from pelvislab.app.commands.gap import GapReport
    from pelvislab.app.gui_replay import ReplayView

    view = ReplayView()
    qtbot.addWidget(view)
    view.show_gap(GapReport(doc, None, [], np.array([]), None))
    shrinks = [view.candidate_table.item(r, 3).text()
               for r in range(view.candidate_table.rowCount())]
    assert shrinks and set(shrinks) <= {"—", "(—)"}
    assert "no shrink can be measured" in view.gap_summary.text()


SHARE_LISTS = ("bands", "outputs", "bones", "inputs")


def test_where_shares_of_the_cli_json_sum_to_1(demo_gap):
    where = demo_gap[3]["where"]
    for key in SHARE_LISTS:
        shares = [item["share"] for item in where[key]]
        assert shares and abs(sum(shares) - 1.0) <= 1e-9, (key, sum(shares))
        assert shares == sorted(shares, reverse=True), key


@pytest.mark.parametrize("key", SHARE_LISTS)
def test_where_shares_sum_to_1_where_4_digits_did_not(key):
    """Equal thirds and sixths: 0.3333 x 3 and 0.1667 x 6 missed 1 by 1e-4 and 2e-4."""
    from pelvislab.model.gap import prepare_data, where_analysis

    f = np.arange(5.0, 300.1, 5.0)  # 60 lines, 10 in each of the 6 bands
    outs = Channels(["sacrum_x", "sias_R_x", "sias_L_x"],
                    ["sacrum", "innominate_right", "innominate_left"],
                    np.array([[-0.16, 0.0, -0.06], [0.0, -0.11, 0.0], [0.0, 0.11, 0.0]]),
                    np.array([[-1.0, 0, 0], [1, 0, 0], [1, 0, 0]]))
    ins = Channels(["sips_R_x", "sips_L_x", "sacrum_x"],
                   ["innominate_right", "innominate_left", "sacrum"],
                   np.array([[-0.14, -0.045, 0.02], [-0.14, 0.045, 0.02], [-0.16, 0, -0.06]]),
                   np.array([[1.0, 0, 0], [1, 0, 0], [1, 0, 0]]))
    H = np.ones((f.size, 3, 3), complex)
    data = prepare_data(f, H, np.ones(H.shape), outs, ins)
    where = where_analysis(data, H + 3.0)  # the same excess residual on every line
    shares = [item["share"] for item in where[key]]
    assert len(shares) == (6 if key == "bands" else 3)
    assert abs(sum(shares) - 1.0) <= 1e-9, shares
