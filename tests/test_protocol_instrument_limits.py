"""Settings the bench's instruments refuse are found before anything is written (audit:
``gain_db = 70`` passed ``protocol check --strict``; ``run`` then failed as an instrument
fault, exit 3, and left a 0-step session file that blocked the name for the next try)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pelvislab.acquisition.protocol import ProtocolError
from pelvislab.app.cli import main
from tests.test_protocol_schema import base, problems_of

DEMO = Path(__file__).resolve().parents[1] / "protocols" / "demo.toml"

REAL_BENCH = """\
[bench]
name = "lab 3"
[limits]
max_drive_vpp = 2.0
max_trigger_vpp = 10.0
[calibration]
drive_newton_per_volt = 8.0
[trigger]
resource = "USB0::0x0957::0x0407::MY44000001::INSTR"
load_ohm = 50
[drive]
resource = "USB0::0x0957::0x0407::MY44000002::INSTR"
load_ohm = "inf"
[digitizer]
resource = "PCI::INSTR0"
[[pulsers]]
resource = "COM3"
"""


def _demo_with(tmp_path: Path, line: str) -> Path:
    text = DEMO.read_text(encoding="utf-8")
    assert "\ndelay_s = 10e-6\n" in text
    path = tmp_path / "p.toml"
    path.write_text(text.replace("\ndelay_s = 10e-6\n", f"\ndelay_s = 10e-6\n{line}\n"),
                    encoding="utf-8")
    return path


PULSER_CASES = [
    ("gain_db = 70", "ultrasound.gain_db", ["gain_db = 70 dB", "-20..59 dB in 1 dB steps"]),
    ("high_pass_hz = 1", "ultrasound.high_pass_hz",
     ["high_pass_hz = 1 Hz", "none, 1e+06 Hz"]),
    ("damping_ohm = 5000", "ultrasound.damping_ohm",
     ["damping_ohm = 5000 ohm", "50, 100, 200, 500 ohm"]),
]


@pytest.mark.parametrize("line, key, words", PULSER_CASES)
def test_check_refuses_pulser_settings_the_simulated_bench_refuses(tmp_path, capsys, line,
                                                                    key, words):
    path = _demo_with(tmp_path, line)
    assert main(["protocol", "check", str(path), "--strict"]) == 1
    captured = capsys.readouterr()
    assert "ok" not in captured.out.split()
    err = captured.err.strip()
    assert "\n" not in err  # one line
    assert err.startswith(f"pelvislab protocol check: error: {path}: {key}: ")
    # the setting, the value, the allowed range and the instrument
    for word in words + ["Panametrics 5077PR", "pulsers[0], pulsers[1] of simulated bench"]:
        assert word in err, (word, err)


def test_run_refuses_them_before_any_file_and_the_name_stays_free(tmp_path, capsys):
    path = _demo_with(tmp_path, "gain_db = 70")
    out = tmp_path / "gain70.h5"
    for _ in range(2):  # the second try was "gain70.h5 exists; not overwriting it"
        assert main(["run", str(path), "--out", str(out), "--quiet"]) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith("pelvislab run: error: ") and "\n" not in err
        assert "ultrasound.gain_db" in err and "-20..59 dB" in err and "exists" not in err
        assert not out.exists()


def test_check_with_a_bench_file_uses_its_instruments(tmp_path, capsys):
    bench = tmp_path / "lab3.toml"
    bench.write_text(REAL_BENCH, encoding="utf-8")  # nothing is opened by the check
    path = _demo_with(tmp_path, "gain_db = 70\nfull_scale_v = 10.0")
    assert main(["protocol", "check", str(path), "--bench", str(bench)]) == 1
    err = capsys.readouterr().err
    # its one pulser (channel 1); the Acqiris driver's own full-scale range
    assert ("ultrasound.gain_db: the Panametrics 5077PR (pulsers[0] of lab 3) refuses it: "
            "gain_db = 70 dB outside -20..59 dB in 1 dB steps") in err
    assert ("ultrasound.full_scale_v: the Acqiris DP235 (digitizer of lab 3) refuses it: "
            "full_scale_v 10.0 outside [0.05, 5] V") in err
    path = _demo_with(tmp_path, "gain_db = 59")
    assert main(["protocol", "check", str(path), "--bench", str(bench)]) == 0


def test_trigger_burst_and_digitizer_record_are_checked_as_the_run_configures_them():
    data = base()
    del data["sweep"]["periods_per_step"]
    data["sweep"].update(start_hz=80.0, stop_hz=280.0, step_hz=100.0)
    data["ultrasound"].update(pulses=60000, samples=100)  # 6e6 samples: fits the memory
    message = problems_of(data)
    assert ("ultrasound.pulses: the Agilent 33220A (trigger of simulated bench) refuses it: "
            "n_pulses must be an integer in [1, 50000]") in message
    data = base()
    data["ultrasound"].update(trigger_width_s=1e-9, offset_v=3.0)
    message = problems_of(data)
    assert "ultrasound.trigger_width_s: the Agilent 33220A" in message
    assert "below the minimum 2e-08 s" in message
    assert ("ultrasound.offset_v: the simulated Acqiris DP235 (digitizer of simulated bench)"
            " refuses it: offset_v must be within +-2 full scales, got 3.0") in message
    # a key the file's own rules already refuse is said once, by them
    data = base()
    data["ultrasound"]["gain_db"] = 90.0
    message = problems_of(data)
    assert message.count("ultrasound.gain_db") == 1 and "must be <= 80 dB" in message


def test_a_limit_only_the_open_instrument_knows_stops_the_run_before_the_file(tmp_path):
    # a pulser whose range is narrower than its driver class says (as a model that told
    # it at open would be): found by asking the open instruments, before the file exists
    from pelvislab.acquisition.runner import prepare_session
    from pelvislab.drivers.interfaces import LimitError
    from pelvislab.sim_instruments.bench import open_simulated_bench

    bench = open_simulated_bench(generators="python")
    pulser = bench.pulsers[0]
    class_check = pulser.check_configuration

    def narrower(gain_db, *args):
        if gain_db > 30:
            raise LimitError(f"gain_db = {gain_db:g} dB outside -20..30 dB", "gain_db")
        class_check(gain_db, *args)

    pulser.check_configuration = narrower
    out = tmp_path / "s.h5"
    with pytest.raises(ProtocolError, match=r"ultrasound\.gain_db: .*\(pulsers\[0\] of "
                                            r"simulated bench\) refuses it: gain_db = 40 dB "
                                            r"outside -20\.\.30 dB"):
        prepare_session(DEMO, out, bench=bench)
    assert not out.exists()
    assert not bench.world.drive.output and not bench.world.trigger.output
    assert bench._closed  # closed with the failed preparation, as for any bad input
