"""A drive chain calibrated per frequency (bench file ``drive_calibration_file``).

A real amplifier + shaker chain's N/V varies with frequency (roll-off, armature); one
constant made every FRF line carry that variation. The table is read, interpolated
(log-magnitude and phase), refused outside its range, recorded in ``/bench`` and divided
out of each step's force.
"""

from __future__ import annotations

import cmath
import math
import re

import numpy as np
import pytest

from pelvislab.acquisition.frf_lines import calibrated_newton_per_volt, drive_calibration_at
from pelvislab.acquisition.protocol import BenchLimits, ProtocolError, load_protocol
from pelvislab.acquisition.runner import bench_differences, force_phasor, prepare_session
from pelvislab.acquisition.session import SessionReader
from pelvislab.drivers.bench import BenchConfig, BenchConfigError
from pelvislab.tests.test_runner_drive import HEAD, assert_frf_matches_model

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")

# a chain rolling off to half its gain and turning 80 degrees between 20 and 200 Hz
TABLE_HZ = (20.0, 100.0, 200.0)
TABLE_N_PER_V = (8.0 + 0j, cmath.rect(6.0, math.radians(-35.0)),
                 cmath.rect(4.0, math.radians(-80.0)))


def write_bench(tmp_path, csv_text: str | None = None, calibration: str | None = None):
    if csv_text is None:
        rows = zip(TABLE_HZ, TABLE_N_PER_V, strict=True)
        csv_text = ("# measured with an impedance head\nfrequency_hz,newton_per_volt_re,"
                    "newton_per_volt_im\n"
                    + "".join(f"{f:g},{g.real!r},{g.imag!r}\n" for f, g in rows))
    (tmp_path / "cal.csv").write_text(csv_text, encoding="utf-8")
    if calibration is None:
        calibration = 'drive_calibration_file = "cal.csv"'
    path = tmp_path / "bench.toml"
    path.write_text("[bench]\nsimulated = true\n[limits]\nmax_drive_vpp = 2.0\n"
                    f"[calibration]\n{calibration}\n", encoding="utf-8")
    return path


def test_interpolation_is_exact_at_the_rows_and_log_linear_between():
    got = drive_calibration_at(np.array(TABLE_HZ), TABLE_HZ, TABLE_N_PER_V)
    assert got == pytest.approx(np.array(TABLE_N_PER_V), rel=1e-12)
    mid = complex(drive_calibration_at(60.0, TABLE_HZ, TABLE_N_PER_V))
    assert abs(mid) == pytest.approx(math.sqrt(8.0 * 6.0), rel=1e-12)
    assert math.degrees(cmath.phase(mid)) == pytest.approx(-17.5, abs=1e-9)


def test_phase_is_unwrapped_across_180_degrees():
    # +170 deg then -170 deg is a 20 degree turn, not 340 back through zero
    table = (cmath.rect(1.0, math.radians(170.0)), cmath.rect(1.0, math.radians(-170.0)))
    mid = complex(drive_calibration_at(15.0, (10.0, 20.0), table))
    assert abs(abs(math.degrees(cmath.phase(mid))) - 180.0) < 1e-9
    assert abs(mid) == pytest.approx(1.0)


def test_no_extrapolation_and_constant_without_a_table():
    with pytest.raises(ValueError, match="250 Hz is outside the drive calibration's range "
                                         "20-200 Hz"):
        drive_calibration_at(250.0, TABLE_HZ, TABLE_N_PER_V)
    with pytest.raises(ValueError, match="outside"):
        drive_calibration_at(np.array([30.0, 10.0]), TABLE_HZ, TABLE_N_PER_V)
    assert calibrated_newton_per_volt(250.0, 8.5 - 0.4j) == 8.5 - 0.4j


def test_bench_file_reads_the_table_relative_to_itself(tmp_path):
    cfg = BenchConfig.load(write_bench(tmp_path))
    assert cfg.drive_calibration_frequency_hz == TABLE_HZ
    assert cfg.drive_calibration_newton_per_volt == pytest.approx(TABLE_N_PER_V)
    assert cfg.drive_calibration_range_hz == (20.0, 200.0)
    assert cfg.drive_calibration_source == tmp_path / "cal.csv"
    assert cmath.isnan(cfg.drive_newton_per_volt)  # no constant that could be used by mistake


def test_magnitude_and_phase_columns(tmp_path):
    text = "frequency_hz,newton_per_volt_abs,newton_per_volt_phase_deg\n" + "".join(
        f"{f:g},{abs(g)!r},{math.degrees(cmath.phase(g))!r}\n"
        for f, g in zip(TABLE_HZ, TABLE_N_PER_V, strict=True))
    cfg = BenchConfig.load(write_bench(tmp_path, text))
    assert cfg.drive_calibration_newton_per_volt == pytest.approx(TABLE_N_PER_V, rel=1e-12)


@pytest.mark.parametrize("text, message", [
    ("f,re,im\n10,1,0\n20,1,0\n", "cal.csv:1: the first line must name the columns"),
    ("frequency_hz,newton_per_volt_re,newton_per_volt_im\n10,1,0\n", "at least two rows"),
    ("frequency_hz,newton_per_volt_re,newton_per_volt_im\n10,1,0\n10,1,0\n",
     "cal.csv:3: frequencies must increase strictly"),
    ("frequency_hz,newton_per_volt_re,newton_per_volt_im\n10,1,0\n20,0,0\n",
     "cal.csv:3: the N/V value must be finite and non-zero"),
    ("frequency_hz,newton_per_volt_re,newton_per_volt_im\n10,1,0\n20,x,0\n",
     "cal.csv:3: not numbers"),
    ("frequency_hz,newton_per_volt_re,newton_per_volt_im\n10,1\n20,1,0\n",
     "cal.csv:2: 3 values expected, got 2"),
    ("frequency_hz,newton_per_volt_abs,newton_per_volt_phase_deg\n10,-1,0\n20,1,0\n",
     "cal.csv:2: the N/V value must be finite and non-zero"),
    # a coarse table across a resonance: -200 deg read as +160 would flip the force
    ("frequency_hz,newton_per_volt_abs,newton_per_volt_phase_deg\n10,1,0\n20,1,-200\n",
     "cal.csv:3: the phase turns +160 deg (the short way round) from 10 to 20 Hz, more than "
     "90 deg"),
    ('frequency_hz,newton_per_volt_re,newton_per_volt_im\n10,1,0\n"20,1,0\n',
     "cal.csv:3: not a CSV line"),
    ("frequency_hz,newton_per_volt_re,newton_per_volt_im\n10,1,0\n20,-1,0.1\n",
     "cal.csv:3: the phase turns +174 deg"),
    ("frequency_hz;newton_per_volt_re;newton_per_volt_im\n10;8,5;0\n",
     "cal.csv:1: separated by ';' ('frequency_hz;newton_per_volt_re;newton_per_volt_im'; "
     "a European spreadsheet?)"),
    ("freq,re,im\n", "(each optionally followed by ,u_rel; read: 'freq,re,im')"),
])
def test_a_bad_calibration_file_is_named_with_its_line(tmp_path, text, message):
    with pytest.raises(BenchConfigError, match="calibration.drive_calibration_file: .*"
                                               + re.escape(message)):
        BenchConfig.load(write_bench(tmp_path, text))


def test_a_phase_wrapped_at_180_degrees_is_a_short_turn(tmp_path):
    # review: 170 then -175 deg (15 deg) was refused as a -345 deg turn, "add rows"
    text = ("frequency_hz,newton_per_volt_abs,newton_per_volt_phase_deg\n"
            "10,8,170\n20,8,-175\n30,8,-160\n")
    cfg = BenchConfig.load(write_bench(tmp_path, text))
    mid = complex(drive_calibration_at(15.0, cfg.drive_calibration_frequency_hz,
                                       cfg.drive_calibration_newton_per_volt))
    assert math.degrees(cmath.phase(mid)) == pytest.approx(177.5)


def test_spreadsheet_exports_are_read(tmp_path):
    # "CSV UTF-8" (byte-order mark), a separator after every row, a comment in cp1252
    text = ("\ufefffrequency_hz,newton_per_volt_re,newton_per_volt_im,\r\n"
            "10,8,0,\t\r\n20,7,-1,\r\n")
    path = write_bench(tmp_path)
    (tmp_path / "cal.csv").write_bytes(text.encode("utf-8") + "# 25 \xb0C\r\n".encode("cp1252"))
    cfg = BenchConfig.load(path)
    assert cfg.drive_calibration_frequency_hz == (10.0, 20.0)
    assert cfg.drive_calibration_newton_per_volt == (8 + 0j, 7 - 1j)


def test_constant_and_table_together_or_a_missing_file_are_refused(tmp_path):
    both = 'drive_newton_per_volt = 8.0\ndrive_calibration_file = "cal.csv"'
    with pytest.raises(BenchConfigError, match="either drive_newton_per_volt .* not both"):
        BenchConfig.load(write_bench(tmp_path, calibration=both))
    with pytest.raises(BenchConfigError, match="file not found: .*nowhere.csv"):
        BenchConfig.load(write_bench(tmp_path, calibration='drive_calibration_file = '
                                                           '"nowhere.csv"'))


PROTOCOL_SWEEP = "[sweep]\nfrequencies_hz = [{}]\ndrive_vpp = 0.2\nperiods_per_step = 10\n"


def test_a_sweep_beyond_the_calibration_is_refused_before_anything_opens(tmp_path):
    cfg = BenchConfig.load(write_bench(tmp_path))
    protocol = tmp_path / "p.toml"
    protocol.write_text(HEAD + PROTOCOL_SWEEP.format("10.0, 40.0, 250.0, 300.0"))
    with pytest.raises(ProtocolError) as caught:
        load_protocol(protocol, BenchLimits.from_config(cfg))
    assert caught.value.problems == [
        "sweep.frequencies_hz: 1 of 4 frequencies (10 Hz) below 20 Hz, outside the drive "
        "calibration of bench (20-200 Hz), which is not extrapolated: calibrate the drive "
        "chain over the sweep, or narrow the sweep",
        "sweep.frequencies_hz: 2 of 4 frequencies (250-300 Hz) above 200 Hz, outside the "
        "drive calibration of bench (20-200 Hz), which is not extrapolated: calibrate the "
        "drive chain over the sweep, or narrow the sweep"]
    ranged = tmp_path / "ranged.toml"
    ranged.write_text(HEAD + "[sweep]\nstart_hz = 10.0\nstop_hz = 100.0\nstep_hz = 10.0\n"
                      "drive_vpp = 0.2\nperiods_per_step = 10\n")
    with pytest.raises(ProtocolError, match=r"sweep\.start_hz: 1 of 10 frequencies \(10 Hz\) "
                                            r"below 20 Hz"):
        load_protocol(ranged, BenchLimits.from_config(cfg))
    load_protocol(protocol)  # one constant N/V: no range to keep to
    # a table written in kHz lies wholly below the sweep: said so
    khz = BenchConfig.load(write_bench(tmp_path, "frequency_hz,newton_per_volt_re,"
                                       "newton_per_volt_im\n0.005,8,0\n0.4,7,-1\n"))
    with pytest.raises(ProtocolError, match=r"\(0.005-0.4 Hz\).*its rows x 1000 would cover "
                                            r"the sweep: kHz in its frequency_hz column\?"):
        load_protocol(protocol, BenchLimits.from_config(khz))
    overlapping = BenchConfig.load(write_bench(tmp_path, "frequency_hz,newton_per_volt_re,"
                                               "newton_per_volt_im\n0.001,8,0\n20,7,-1\n"))
    with pytest.raises(ProtocolError, match=r"3 of 4 frequencies \(40-300 Hz\) above 20 Hz"
                                            r".*kHz in its frequency_hz column\?"):
        load_protocol(protocol, BenchLimits.from_config(overlapping))
    bench_path = tmp_path / "bench.toml"
    with pytest.raises(ProtocolError, match="outside the drive calibration"):
        prepare_session(protocol, tmp_path / "s.h5", bench_path=bench_path)
    assert not (tmp_path / "s.h5").exists()


def test_each_step_divides_by_its_own_frequency_calibration(tmp_path):
    cfg = BenchConfig.load(write_bench(tmp_path))
    protocol = tmp_path / "p.toml"
    protocol.write_text(HEAD + PROTOCOL_SWEEP.format("40.0, 160.0"))
    bench = sim_bench.open_simulated_bench(cfg, generators="python")
    with prepare_session(protocol, tmp_path / "s.h5", bench=bench) as session:
        assert session.run().status == "completed"
    with SessionReader(tmp_path / "s.h5") as reader:
        steps = list(reader.steps(with_echoes=False))
        measured = reader.frf()
        recorded = reader.bench()
    for s in steps:
        n_per_v = complex(drive_calibration_at(s.frequency_hz, TABLE_HZ, TABLE_N_PER_V))
        assert s.force_phasor_n == pytest.approx(force_phasor(s.frequency_hz, 0.2, n_per_v))
    # the simulated chain follows the table: the FRF is the model's, at both frequencies
    # (the 40 Hz value used at 160 Hz would read H 0.63x at -53 degrees)
    assert_frf_matches_model(measured)
    assert recorded["drive_calibration_frequency_hz"] == pytest.approx(TABLE_HZ)
    assert recorded["drive_calibration_newton_per_volt"] == pytest.approx(TABLE_N_PER_V)
    assert recorded["drive_calibration_file"].endswith("cal.csv")


def test_resume_compares_the_table(tmp_path):
    table = {"simulated": True, "drive_newton_per_volt": complex("nan+nanj"),
             "speed_of_sound_m_s": 1540.0,
             "drive_calibration_frequency_hz": np.array(TABLE_HZ),
             "drive_calibration_newton_per_volt": np.array(TABLE_N_PER_V)}
    assert bench_differences(table, dict(table)) == []
    values = np.array(TABLE_N_PER_V)
    values[1] *= 1.1
    other = dict(table, drive_calibration_newton_per_volt=values)
    assert bench_differences(table, other) == [
        "drive calibration (drive_calibration_newton_per_volt): a per-frequency table (3 "
        "rows, 20-200 Hz) in the session, another table (first different at 100 Hz: "
        f"{TABLE_N_PER_V[1]:.10g} -> {values[1]:.10g} N/V) now"]
    # review: differences the comparison sees but 4 digits do not, and a moved inner row
    close = np.array(TABLE_N_PER_V)
    close[0] = 8.0000001
    (line,) = bench_differences(table, dict(table, drive_calibration_newton_per_volt=close))
    assert "first different at 20 Hz: 8+0j -> 8.0000001+0j N/V" in line
    moved = dict(table, drive_calibration_frequency_hz=np.array([20.0, 110.0, 200.0]))
    (line,) = bench_differences(table, moved)
    assert "another table (row 2 at 110 Hz, was 100 Hz) now" in line
    constant = {"simulated": True, "drive_newton_per_volt": 8.0, "speed_of_sound_m_s": 1540.0}
    (line,) = bench_differences(table, constant)
    assert line.endswith("a per-frequency table (3 rows, 20-200 Hz) in the session, one "
                         "constant 8+0j N/V now")
    other_constant = dict(constant, drive_newton_per_volt=8.000001)
    assert bench_differences(constant, other_constant) == [
        "drive calibration (drive_newton_per_volt): one constant 8+0j N/V in the session, "
        "one constant 8.000001+0j N/V now"]
    assert bench_differences(constant, table) == [
        "drive calibration (drive_newton_per_volt): one constant 8+0j N/V in the session, "
        "a per-frequency table (3 rows, 20-200 Hz) now"]


def test_resume_on_the_same_table_through_the_file(tmp_path):
    cfg = BenchConfig.load(write_bench(tmp_path))
    protocol = tmp_path / "p.toml"
    protocol.write_text(HEAD + PROTOCOL_SWEEP.format("40.0, 160.0"))
    out = tmp_path / "s.h5"
    with prepare_session(protocol, out, bench=sim_bench.open_simulated_bench(
            cfg, generators="python")) as session:
        session.runner.abort("stopped for the test")
        session.run()
    aborted = tmp_path / "aborted.h5"  # a finished session is not resumed at all
    aborted.write_bytes(out.read_bytes())
    with prepare_session(protocol, out, resume=True, bench=sim_bench.open_simulated_bench(
            cfg, generators="python")) as session:
        assert session.run().status == "completed"
    (tmp_path / "cal.csv").write_text((tmp_path / "cal.csv").read_text().replace(
        "20,", "10,"))
    with pytest.raises(ValueError, match=r"drive calibration \(drive_calibration_frequency_hz"
                                         r"\): a per-frequency table \(3 rows, 20-200 Hz\) in "
                                         r"the session, another table \(row 1 at 10 Hz, "
                                         r"was 20 Hz\)"):
        prepare_session(protocol, aborted, resume=True, bench=sim_bench.open_simulated_bench(
            BenchConfig.load(tmp_path / "bench.toml"), generators="python"))


def test_bench_check_names_the_table(tmp_path, capsys):
    from pelvislab.app.cli import main

    assert main(["bench", "check", str(write_bench(tmp_path))]) == 0
    out = capsys.readouterr().out
    assert (f"  drive calibration: 3 rows, 20-200 Hz (not extrapolated), from "
            f"{tmp_path / 'cal.csv'}\n") in out


def test_a_runner_made_directly_refuses_a_step_outside_the_table_before_any_prompt(tmp_path):
    # review: a Runner built without parse_protocol's bench limits failed at the first
    # step outside the table, after the prompt and two measured steps
    from pelvislab.acquisition.runner import Runner, SetupStarted

    cfg = BenchConfig.load(write_bench(tmp_path))
    protocol = tmp_path / "p.toml"
    protocol.write_text(HEAD + PROTOCOL_SWEEP.format("40.0, 160.0, 250.0"))
    bench = sim_bench.open_simulated_bench(cfg, generators="python")
    runner = Runner(load_protocol(protocol), bench)
    events = []
    runner.subscribe(events.append)
    try:
        final = runner.run()
    finally:
        bench.close()
    assert final.status == "failed" and final.n_done == 0
    assert "250 Hz is outside the drive calibration's range 20-200 Hz" in final.reason
    assert not any(isinstance(e, SetupStarted) for e in events)
