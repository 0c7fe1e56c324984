"""The drive calibration's uncertainty: stated in the bench file, recorded, used by identify.

One shaker, amplifier and calibration (N/V) drive every input, so an error in the
calibration scales every FRF alike: a common scale of masses, stiffnesses and dampings that
the data cannot tell from it. Identify's std held only the noise's share: a 3 % calibration
error on a simulated session gave the parameters 3 % off with std of 0.1-1.4 % (sum of z^2
over 18 parameters ~3100 where ~18 is expected).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from pelvislab.drivers.bench import BenchConfig, BenchConfigError
from pelvislab.tests.test_drive_calibration import TABLE_HZ, TABLE_N_PER_V, write_bench

DATA = Path(__file__).parent / "data" / "demo_sim_seed1.h5"  # simulated chain, /frf only


def _table_csv(u_rel=(0.01, 0.02, 0.04)) -> str:
    return ("frequency_hz,newton_per_volt_re,newton_per_volt_im,u_rel\n"
            + "".join(f"{f:g},{g.real!r},{g.imag!r},{u:g}\n"
                      for f, g, u in zip(TABLE_HZ, TABLE_N_PER_V, u_rel, strict=True)))


def test_a_u_rel_column_and_a_constants_uncertainty_are_read(tmp_path):
    cfg = BenchConfig.load(write_bench(tmp_path, _table_csv()))
    assert cfg.drive_calibration_u_rel == (0.01, 0.02, 0.04)
    assert cfg.drive_calibration_frequency_hz == TABLE_HZ
    cfg = BenchConfig.load(write_bench(tmp_path, calibration="drive_newton_per_volt = 9.0\n"
                                                   "drive_newton_per_volt_u_rel = 0.02"))
    assert cfg.drive_calibration_u_rel == (0.02,)
    assert BenchConfig.load(write_bench(tmp_path)).drive_calibration_u_rel == ()


@pytest.mark.parametrize("csv_row, problem", [
    ("100,6.0,-3.0,-0.01", r"cal.csv:3: u_rel must be a fraction in \[0, 0.2\]"),
    ("100,6.0,-3.0,2", r"cal.csv:3: u_rel must be a fraction in \[0, 0.2\] \(e.g. 0.02 for "
                       r"2 %\), got 2"),
    # a certificate's 0.3 % typed as 0.3: 30 % (review)
    ("100,6.0,-3.0,0.3", r"cal.csv:3: u_rel must be a fraction in \[0, 0.2\]"),
    ("100,6.0,-3.0", r"cal.csv:3: 4 values expected, got 3"),
])
def test_a_bad_u_rel_names_its_line(tmp_path, csv_row, problem):
    text = ("frequency_hz,newton_per_volt_re,newton_per_volt_im,u_rel\n20,8.0,0.0,0.01\n"
            f"{csv_row}\n200,4.0,-3.9,0.02\n")
    with pytest.raises(BenchConfigError, match=problem):
        BenchConfig.load(write_bench(tmp_path, text))


def test_a_constants_uncertainty_is_checked_and_not_given_with_a_table(tmp_path):
    with pytest.raises(BenchConfigError, match="drive_newton_per_volt_u_rel: must be a "
                                               "fraction"):
        BenchConfig.load(write_bench(tmp_path, calibration="drive_newton_per_volt = 9.0\n"
                                                          "drive_newton_per_volt_u_rel = 3"))
    with pytest.raises(BenchConfigError, match="u_rel column"):
        BenchConfig.load(write_bench(
            tmp_path, calibration='drive_calibration_file = "cal.csv"\n'
                                  "drive_newton_per_volt_u_rel = 0.02"))


def test_recorded_in_bench_and_said_by_bench_check(tmp_path, capsys):
    from pelvislab.acquisition.session import SessionReader, bench_description
    from pelvislab.app.cli import main
    from pelvislab.sim_instruments.bench import open_simulated_bench

    cfg = BenchConfig.load(write_bench(tmp_path, _table_csv()))
    bench = open_simulated_bench(cfg, generators="python")
    try:
        described = bench_description(bench)
    finally:
        bench.close()
    assert described["drive_calibration_u_rel"] == pytest.approx([0.01, 0.02, 0.04])
    assert main(["bench", "check", str(tmp_path / "bench.toml")]) == 0
    assert "3 rows, 20-200 Hz (not extrapolated), u = 1-4 % (k = 1), from" in \
        capsys.readouterr().out
    del SessionReader  # (recording goes through bench_description: the session writer's)


def _session_with_bench(tmp_path: Path, name: str, **attrs) -> Path:
    """The simulated demo session's /frf with a /bench group holding ``attrs``."""
    path = tmp_path / name
    shutil.copy(DATA, path)
    with h5py.File(path, "a") as handle:
        bench = handle.create_group("bench")
        for key, value in attrs.items():
            bench.attrs[key] = value
    return path


def test_identify_marginalises_the_calibration_and_its_std_then_cover_a_3_percent_error():
    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.identification import default_strategy, identify_frf
    from pelvislab.model.identification_pelvis import pelvis_problem
    from pelvislab.model.pelvis import default_model

    frf = read_frf(DATA)
    problem, _ = pelvis_problem(default_model(), frf.outputs, frf.inputs)
    truth = np.array(problem.nominal)
    # a calibration 3 % off: every FRF (and its noise) 3 % high
    fits = [identify_frf(problem, frf.frequency_hz, 1.03 * frf.H, 1.03 * frf.H_std,
                         strategy=default_strategy("std"), chain_gain_std=u)
            for u in (0.0, 0.03)]
    np.testing.assert_array_equal(fits[0].values, fits[1].values)  # the fit is the same
    z2 = [float(np.sum(((f.values - truth) / f.std) ** 2)) for f in fits]
    assert z2[0] > 1000 and z2[1] < 40, z2  # measured 3091 and ~19
    masses = [problem.names.index(n) for n in ("m_innominate_right", "m_sacrum")]
    assert np.all(fits[1].std[masses] / fits[1].values[masses] > 0.025)
    with pytest.raises(ValueError, match="chain_gain_std"):
        identify_frf(problem, frf.frequency_hz, frf.H, frf.H_std, chain_gain_std=np.nan)


def test_identify_takes_the_sessions_recorded_uncertainty(tmp_path, capsys):
    from pelvislab.app.cli import main
    from pelvislab.app.commands.identify import recorded_calibration_std

    table = _session_with_bench(
        tmp_path, "table.h5", simulated=False,
        drive_calibration_frequency_hz=np.array([1.0, 500.0]),
        drive_calibration_u_rel=np.array([0.02, 0.02]))
    one = _session_with_bench(tmp_path, "one.h5", simulated=False,
                              drive_calibration_u_rel=np.array([0.015]))
    unstated = _session_with_bench(tmp_path, "unstated.h5", simulated=False)
    simulated = _session_with_bench(tmp_path, "sim.h5", simulated=True)
    assert recorded_calibration_std(table, [10.0, 200.0])[:2] == (pytest.approx(0.02), "bench")
    # a table's rms over the lines: 1 % and 3 % at two lines -> sqrt((1 + 9) / 2) %
    ramp = _session_with_bench(tmp_path, "ramp.h5", simulated=False,
                               drive_calibration_frequency_hz=np.array([0.0, 300.0]),
                               drive_calibration_u_rel=np.array([0.0, 0.03]))
    assert recorded_calibration_std(ramp, [100.0, 300.0])[0] == pytest.approx(
        np.sqrt((0.01 ** 2 + 0.03 ** 2) / 2))
    assert recorded_calibration_std(one, [10.0])[:2] == (0.015, "bench")
    # resumed after the bench file stated it: the latest run's bench counts (/bench is the
    # first run's)
    with h5py.File(unstated, "a") as handle:
        for n, u in (("000", None), ("001", 0.01)):
            run_bench = handle.create_group(f"runs/{n}/bench")
            run_bench.attrs["simulated"] = False
            if u is not None:
                run_bench.attrs["drive_calibration_u_rel"] = np.array([u])
    assert recorded_calibration_std(unstated, [10.0])[:2] == (0.01, "bench")
    unstated = _session_with_bench(tmp_path, "unstated2.h5", simulated=False)
    assert recorded_calibration_std(DATA, [10.0]) == (0.0, "none", None)  # FRF-only
    assert recorded_calibration_std(simulated, [10.0]) == (0.0, "none", None)
    value, source, note = recorded_calibration_std(unstated, [10.0])
    assert (value, source) == (0.0, "none") and "stated no uncertainty" in note

    out = tmp_path / "id.json"
    fast = ["--starts", "1"]  # the std's terms are the point, not the search
    assert main(["identify", str(one), *fast, "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert (doc["calibration_std"], doc["calibration_std_source"]) == (0.015, "bench")
    out2 = tmp_path / "id2.json"
    assert main(["identify", str(one), *fast, "--calibration-std", "0", "--json",
                 str(out2)]) == 0
    doc2 = json.loads(out2.read_text())
    assert (doc2["calibration_std"], doc2["calibration_std_source"]) == (0.0, "option")
    # the std grow with it (k_io_R: a scale of the whole model), the values stay
    k_io = [d["parameters"]["k_io_R"] for d in (doc, doc2)]
    assert k_io[0]["value"] == k_io[1]["value"] and k_io[0]["std"] > 1.3 * k_io[1]["std"]
    capsys.readouterr()
    assert main(["identify", str(unstated), *fast, "--json", str(tmp_path / "u.json")]) == 0
    assert "note: the bench file stated no uncertainty of the drive calibration" in \
        capsys.readouterr().err
    assert main(["identify", str(one), "--calibration-std", "0.6", "--json",
                 str(tmp_path / "bad.json")]) == 1
    assert "--calibration-std 0.6: must be a fraction" in capsys.readouterr().err


def test_a_real_benchs_unstated_uncertainty_is_said():
    from pelvislab.app.commands.bench import drive_calibration_text

    real = BenchConfig(simulated=False, drive_newton_per_volt=complex(9.0, 0.0))
    assert drive_calibration_text(real) == ("9+0j N/V at every frequency; its uncertainty "
                                            "not stated")
    stated = BenchConfig(simulated=False, drive_newton_per_volt=complex(9.0, 0.0),
                         drive_calibration_u_rel=(0.02,))
    assert drive_calibration_text(stated) == "9+0j N/V at every frequency, u = 2 % (k = 1)"
    assert drive_calibration_text(BenchConfig()) == "1+0j N/V at every frequency"  # simulated


@pytest.mark.parametrize("residual, std_factor", [("log", None), ("std", 0.5)])
def test_the_stated_uncertainty_adds_as_stated_whatever_the_misfit(residual, std_factor):
    # the priors were scaled with the data's rms when the covariance was not absolute: a
    # stated 3 % added 0.23 % with the log residual (files without H_std) and 6 % at
    # chi2/dof 4 (review of session 40)
    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.identification import default_strategy, identify_frf
    from pelvislab.model.identification_pelvis import pelvis_problem
    from pelvislab.model.pelvis import default_model

    frf = read_frf(DATA)
    problem, _ = pelvis_problem(default_model(), frf.outputs, frf.inputs)
    H_std = None if std_factor is None else std_factor * frf.H_std
    fits = [identify_frf(problem, frf.frequency_hz, frf.H, H_std,
                         strategy=default_strategy(residual, starts=1), chain_gain_std=u)
            for u in (0.0, 0.03)]
    k = problem.names.index("k_io_R")
    before, after = (f.std[k] / f.values[k] for f in fits)
    assert np.sqrt(after ** 2 - before ** 2) == pytest.approx(0.03, rel=0.05)
