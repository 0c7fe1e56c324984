"""Gap benchmark, full-chain source (issue 10): one tiny session of the simulated bench
(face-up protocol on a 20 Hz grid, 3 periods per step) with a hidden random subject,
carried into the benchmark's scoring with ``source="chain"``. The full run with every
effect kind is ``pelvislab gap benchmark --source chain`` (docs/gap-diagnosis.md)."""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.app.cli import main
from pelvislab.model.frf import frf
from pelvislab.model.gap_benchmark import run_benchmark
from pelvislab.model.gap_effects import EFFECT_NAMES
from pelvislab.model.pelvis import default_model
from pelvislab.tests.benchmarks.bench_gap import (
    INPUTS,
    MEASURED,
    OUTPUTS,
    chain_protocol_text,
    make_chain_generator,
)


@pytest.fixture(scope="module")
def none_case(tmp_path_factory):
    gen = make_chain_generator(seed=3, step_hz=20.0, periods=3,
                               workdir=str(tmp_path_factory.mktemp("chain")))
    return gen("none", 0)


def _rel_error(H: np.ndarray, H_ref: np.ndarray) -> float:
    """Median over measured FRFs of the rms error relative to each FRF's peak."""
    peak = np.maximum(np.max(np.abs(H_ref), axis=0), 1e-30)  # unmeasured pairs are 0
    err = np.sqrt(np.mean(np.abs(H - H_ref) ** 2, axis=0)) / peak
    return float(np.median(err[MEASURED]))


def test_chain_case_is_a_face_up_session_of_the_hidden_subject(none_case):
    case = none_case
    assert case.source == "chain" and case.effect == "none"
    assert sorted(case.outputs.name) == sorted(OUTPUTS.name)
    assert sorted(case.inputs.name) == sorted(INPUTS.name)
    np.testing.assert_allclose(case.frequency_hz, np.arange(5.0, 300.1, 20.0))
    # the session's channel order is its own: bring it to the generator's
    o = [list(case.outputs.name).index(n) for n in OUTPUTS.name]
    i = [list(case.inputs.name).index(n) for n in INPUTS.name]
    H = case.H[:, o][:, :, i]
    measured = np.all(np.isfinite(H), axis=0)
    assert np.array_equal(measured, MEASURED)  # the 15 FRFs of table 6.3, no others
    # the session measured the hidden (perturbed) subject, not appendix E: the chain's
    # FRF agrees with the truth model and clearly not with the nominal one
    H_true = frf(case.truth_model, case.frequency_hz, OUTPUTS, INPUTS)
    H_nom = frf(default_model(), case.frequency_hz, OUTPUTS, INPUTS)
    Hm = np.where(measured[None], H, 0)
    e_true = _rel_error(Hm, np.where(measured[None], H_true, 0))
    e_nom = _rel_error(Hm, np.where(measured[None], H_nom, 0))
    print(f"chain vs truth {e_true:.3f}, vs appendix E {e_nom:.3f}")
    assert e_true < 0.02, e_true
    assert e_nom > 2 * e_true, (e_nom, e_true)
    assert case.params["chain_run_s"] > 0


def test_chain_case_is_scored_with_its_source(none_case):
    result = run_benchmark(None, kinds=["none"], cases_per_kind=0,
                           chain_generator=lambda kind, index: none_case,
                           chain_cases_per_kind=1)
    assert result["n_cases"] == 1
    entry = result["cases"][0]
    assert entry["source"] == "chain" and entry["kind"] == "none"
    assert entry["n_frf"] == 15 and entry["n_lines"] == 15
    assert sum(result["confusion"]["matrix"]["none"].values()) == 1
    # every possible verdict is a column even when only "none" sets were generated
    assert set(EFFECT_NAMES) <= set(result["confusion"]["rows_truth_cols_verdict"])
    assert result["confusion"]["matrix"]["none"][entry["verdict"]] == 1


def test_chain_protocol_is_face_up_on_a_coarser_grid():
    text = chain_protocol_text(10.0, 4, stop_hz=100.0)
    assert "step_hz = 10.0" in text and "periods_per_step = 4" in text
    assert "stop_hz = 100.0" in text and text.count("[[setups]]") == 9


def test_cli_rejects_bad_chain_options(tmp_path, capsys):
    code = main(["gap", "benchmark", "--json", str(tmp_path / "o.json"), "--chain-cases",
                 "-1"])
    assert code == 1
    assert "--chain-cases" in capsys.readouterr().err


def test_named_effect_acts_only_where_its_point_is_placed():
    from pelvislab.sim_instruments.bench import open_simulated_bench
    from pelvislab.sim_instruments.effects import SensorMisorientation, SoftTissue
    from pelvislab.tests.benchmarks.bench_gap import _apply_named_effects_where_placed

    tissue = SoftTissue(inputs=("sacrum_x",))
    tilt = SensorMisorientation(tilt_deg=20.0, outputs=("SIAS_R_x",))
    bench = open_simulated_bench(effects=[tissue, tilt], generators="python")
    try:
        _apply_named_effects_where_placed(bench, [tissue, tilt])
        bench.place(excitation="SIPS_R_x", channels={1: "SIPS_R_x", 2: "SIAS_L_x"})
        assert bench.world.frf_effects == []
        assert all(np.isfinite(v) for v in bench.world.frf(50.0).values())
        bench.place(excitation="sacrum_x", channels={1: "sacrum_x", 2: "SIAS_R_x"})
        assert bench.world.frf_effects == [tissue, tilt]
        assert all(np.isfinite(v) for v in bench.world.frf(50.0).values())
    finally:
        bench.close()
