"""The bench file's speed of sound: which value tracking uses (per-channel bench value >
the bench's value for every channel, on tissue only > the protocol's), recorded on each
echoes dataset,
and compared on resume (an audit found the bench's global value recorded in /bench, given
to the simulated echoes, and never used by the runner: |H| 0.964x at 1600 m/s)."""

from __future__ import annotations

import math

import h5py
import numpy as np
import pytest

from pelvislab.acquisition.runner import StepFinished, prepare_session
from pelvislab.acquisition.session import SessionReader
from pelvislab.drivers.bench import BenchConfig

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")

PROTOCOL = """
schema = "pelvislab-protocol"
schema_version = 1
name = "speed-of-sound"
[sweep]
frequencies_hz = [60.0, 120.0]
drive_vpp = 0.8
settle_s = 0.05
[ultrasound]
pulses = 250
samples = 500
speed_of_sound_m_s = {c}
[[setups]]
name = "a"
excitation = "SIAS_R_x"
transducers = {{ ch1 = "SIAS_R_x", ch2 = "sacrum_x" }}
"""

BENCH = """
[bench]
simulated = true
[limits]
max_drive_vpp = 1.0
[calibration]
drive_newton_per_volt = 1.0
"""


def _files(tmp_path, calibration="", protocol_c=1540.0, name="b"):
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL.format(c=protocol_c))
    bench = tmp_path / f"{name}.toml"
    bench.write_text(BENCH + calibration)
    return protocol, bench


def _run(protocol, bench, out, abort_after=None, truth=None):
    with prepare_session(protocol, out, bench_path=bench) as session:
        if abort_after is not None:
            done = []

            def on_event(event):
                if isinstance(event, StepFinished):
                    done.append(event)
                    if len(done) >= abort_after:
                        session.runner.abort("stopped for the test")

            session.runner.subscribe(on_event)
        final = session.run()
        if truth is not None:
            truth.extend(t for t in session.bench.world.truth if t.drive_on)
        return final


def _used(out):
    """{channel name: set of speeds on its echoes datasets}, the /bench value."""
    used: dict[str, set[float]] = {}
    with SessionReader(out) as reader:
        for step in reader.steps(with_echoes=False):
            for ch in step.channels:
                used.setdefault(ch.name, set()).add(ch.speed_of_sound_m_s)
        return used, reader.bench()["speed_of_sound_m_s"]


def test_the_bench_files_speed_of_sound_is_the_one_tracking_uses(tmp_path):
    protocol, fast = _files(tmp_path, "speed_of_sound_m_s = 1600.0\n")
    truth: list = []
    assert _run(protocol, fast, tmp_path / "fast.h5", truth=truth).status == "completed"
    used, recorded = _used(tmp_path / "fast.h5")
    assert recorded == 1600.0
    # what was used is on each echoes dataset (reprocess reads it there)
    assert used == {"ch1": {1600.0}, "ch2": {1600.0}}
    # the simulated echoes travel at the bench's value and the tracker assumes it: |H| as
    # the simulator's truth (0.9625x before: echoes at 1600 m/s read with 1540 m/s)
    with SessionReader(tmp_path / "fast.h5") as reader:
        measured = [ch.phasor_m for step in reader.steps(with_echoes=False)
                    for ch in step.channels]
    true = [t.measured_phasor_m[ch] for t in truth for ch in (1, 2)]
    assert np.median(np.abs(measured) / np.abs(true)) == pytest.approx(1.0, abs=0.015)


def test_per_channel_value_then_bench_value_then_protocol(tmp_path):
    protocol, both = _files(tmp_path, "speed_of_sound_m_s = 1600.0\n"
                            "[calibration.channel_speed_of_sound_m_s]\n2 = 1560.0\n",
                            protocol_c=1500.0)
    assert _run(protocol, both, tmp_path / "both.h5").status == "completed"
    assert _used(tmp_path / "both.h5")[0] == {"ch1": {1600.0}, "ch2": {1560.0}}
    # a bench file without it: the protocol's, and /bench says the bench states none
    _, plain = _files(tmp_path, protocol_c=1500.0, name="plain")
    truth: list = []
    assert _run(protocol, plain, tmp_path / "plain.h5", truth=truth).status == "completed"
    used, recorded = _used(tmp_path / "plain.h5")
    assert used == {"ch1": {1500.0}, "ch2": {1500.0}} and math.isnan(recorded)
    # the simulated tissue follows the protocol's value when the bench states none, as it
    # follows the bench's: |H| as the simulator's truth (0.974x before: echoes sent at the
    # simulator's own 1540 m/s, read with the protocol's 1500; session 41's note)
    with SessionReader(tmp_path / "plain.h5") as reader:
        measured = [ch.phasor_m for step in reader.steps(with_echoes=False)
                    for ch in step.channels]
    true = [t.measured_phasor_m[ch] for t in truth for ch in (1, 2)]
    assert np.median(np.abs(measured) / np.abs(true)) == pytest.approx(1.0, abs=0.01)
    cfg = BenchConfig.load(both)
    assert [cfg.speed_of_sound_for(ch, 1500.0) for ch in (1, 2)] == [1600.0, 1560.0]
    assert BenchConfig.load(plain).speed_of_sound_for(1, 1500.0) == 1500.0


def test_resume_refuses_a_speed_of_sound_other_than_its_steps(tmp_path):
    protocol, plain = _files(tmp_path)
    _, fast = _files(tmp_path, "speed_of_sound_m_s = 1600.0\n", name="fast")
    out = tmp_path / "s.h5"
    assert _run(protocol, plain, out, abort_after=1).status == "aborted"
    with pytest.raises(ValueError, match=r"another bench \(speed of sound on ch1: 1540 m/s "
                       r"in the session's steps, 1600 m/s now \(the bench file's "
                       r"calibration.speed_of_sound_m_s\); .*ch2"):
        prepare_session(protocol, out, bench_path=fast, resume=True)
    # a session written before the bench's value was applied: /bench said 1600 and its
    # steps were tracked at the protocol's 1540; resuming it on that bench file would now
    # track at 1600: the steps decide, not /bench
    with h5py.File(out, "r+") as h5:
        h5["bench"].attrs["speed_of_sound_m_s"] = 1600.0
    with pytest.raises(ValueError, match="speed of sound on ch1: 1540 m/s") as refused:
        prepare_session(protocol, out, bench_path=fast, resume=True)
    # the refusal says how to go on with that bench file (it may be the session's own)
    fix = "[calibration.channel_speed_of_sound_m_s] 1 = 1540"
    assert fix in str(refused.value)
    _, kept = _files(tmp_path, "speed_of_sound_m_s = 1600.0\n"
                     "[calibration.channel_speed_of_sound_m_s]\n1 = 1540.0\n2 = 1540.0\n",
                     name="kept")
    prepare_session(protocol, out, bench_path=kept, resume=True).close()
    _, same = _files(tmp_path, "speed_of_sound_m_s = 1540.0\n", name="same")
    with prepare_session(protocol, out, bench_path=same, resume=True) as session:
        assert session.run().status == "completed"


def test_the_checks_say_where_the_bench_replaces_the_protocols_value(tmp_path, capsys):
    from pelvislab.app.cli import main

    protocol, bench = _files(tmp_path, "speed_of_sound_m_s = 1600.0\n"
                             "[calibration.channel_speed_of_sound_m_s]\n2 = 1540.0\n")
    assert main(["protocol", "check", str(protocol), "--bench", str(bench)]) == 0
    assert ("note: speed of sound from the bench file: ch1 1600 m/s "
            "(calibration.speed_of_sound_m_s); the protocol's 1540 m/s is not used there"
            ) in capsys.readouterr().err
    assert main(["bench", "check", str(bench)]) == 0
    assert ("  speed of sound: 1600 m/s on every channel (over the protocol's); ch2 1540 m/s"
            "; on tissue: a test object (excitation on no bone) keeps the protocol's"
            ) in capsys.readouterr().out


def _refusals_of_every_command(tmp_path, capsys, protocol, bench):
    """stderr of ``bench check``, ``protocol check --bench`` and ``run --bench``, each of
    which must refuse ``bench`` (exit 1); the run must write no file."""
    from pelvislab.app.cli import main

    out = tmp_path / "s.h5"
    errors = []
    for argv in (["bench", "check", str(bench)],
                 ["protocol", "check", str(protocol), "--bench", str(bench)],
                 ["run", str(protocol), "--bench", str(bench), "--out", str(out)]):
        assert main(argv) == 1, argv
        errors.append(capsys.readouterr().err)
    assert not out.exists()
    return errors


@pytest.mark.parametrize("calibration, key", [
    ("[calibration.channel_speed_of_sound_m_s]\n2 = 15.6\n",
     "calibration.channel_speed_of_sound_m_s.2"),
    ("speed_of_sound_m_s = 15.6\n", "calibration.speed_of_sound_m_s"),
    ("speed_of_sound_m_s = 1.54e6\n", "calibration.speed_of_sound_m_s"),
])
def test_a_speed_of_sound_in_another_unit_is_refused_before_anything_runs(
        tmp_path, capsys, calibration, key):
    # 15.6 for 1560 passed bench check, protocol check --bench and run (only > 0 was
    # checked) and scaled |H| by 0.01 (an audit)

    protocol, bench = _files(tmp_path, calibration)
    for err in _refusals_of_every_command(tmp_path, capsys, protocol, bench):
        assert f"{key}: must be > 100 and <= 10000 m/s, got " in err, err


@pytest.mark.parametrize("c, ok", [(100.0, False), (100.5, True), (10_000.0, True),
                                   (10_000.5, False)])
def test_bench_protocol_and_reprocess_share_one_range(tmp_path, c, ok):
    from pelvislab.acquisition.protocol import ProtocolError, load_protocol
    from pelvislab.acquisition.runner import reprocess_session
    from pelvislab.drivers.bench import BenchConfigError

    protocol, bench = _files(tmp_path, f"speed_of_sound_m_s = {c}\n", protocol_c=c)
    outcomes = []
    for check in (lambda: BenchConfig.load(bench), lambda: load_protocol(protocol)):
        try:
            check()
            outcomes.append(True)
        except (BenchConfigError, ProtocolError):
            outcomes.append(False)
    try:  # refused before the source is even looked for
        reprocess_session(tmp_path / "none.h5", tmp_path / "out.h5", None, c)
    except ValueError as exc:
        outcomes.append("speed of sound" not in str(exc))
    except FileNotFoundError:
        outcomes.append(True)
    assert outcomes == [ok] * 3


def test_a_speed_of_sound_for_a_channel_the_digitizer_lacks_is_refused(tmp_path, capsys):
    # `3 = 1560.0` on the 2-channel DP235 passed every check and was never used (an audit)

    protocol, bench = _files(tmp_path, "[calibration.channel_speed_of_sound_m_s]\n"
                                       "2 = 1560.0\n3 = 1560.0\n")
    for err in _refusals_of_every_command(tmp_path, capsys, protocol, bench):
        assert ("calibration.channel_speed_of_sound_m_s.3: no digitizer channel 3: the "
                "Acqiris DP235 (simulated) has channels 1, 2") in err, err
        assert "channel_speed_of_sound_m_s.2" not in err
    real = (BENCH.replace("simulated = true", "simulated = false")
            + "[calibration.channel_speed_of_sound_m_s]\n3 = 1560.0\n"
            + '[trigger]\nresource = "USB0::1::2::A::INSTR"\nload_ohm = 50\n'
            + '[drive]\nresource = "USB0::1::2::B::INSTR"\nload_ohm = "inf"\n'
            + '[digitizer]\nresource = "PCI::INSTR0"\n[[pulsers]]\nresource = "loop://"\n')
    (tmp_path / "real.toml").write_text(real)
    from pelvislab.drivers.bench import BenchConfigError

    with pytest.raises(BenchConfigError, match=r"\.3: no digitizer channel 3: the Acqiris "
                       r"DP235 has channels 1, 2"):
        BenchConfig.load(tmp_path / "real.toml")


def test_a_test_object_keeps_the_protocols_speed_of_sound(tmp_path):
    """The bench's value for every channel is the tissue's: on a setup whose excitation is
    on no bone (validation_amplitude: the piezo face in water, 1480 m/s) the protocol's
    value holds, as the simulated phantom's echoes keep theirs. A bench file stating 1540
    m/s read the validation amplitudes +4.05 % (review, session 41), and one stating
    1560 m/s for a channel +5.4 % (the next review): per-channel values are the tissue's
    too."""
    from pathlib import Path

    from pelvislab.acquisition.protocol import load_protocol
    from pelvislab.acquisition.runner import speed_of_sound_note

    shipped = Path(__file__).resolve().parents[1] / "protocols" / "validation_amplitude.toml"
    _, plain = _files(tmp_path, "", name="plain")
    _, stated = _files(tmp_path, "speed_of_sound_m_s = 1540.0\n", name="stated")
    _, per_channel = _files(tmp_path, "[calibration.channel_speed_of_sound_m_s]\n1 = 1490.0\n",
                            name="channel")
    config = BenchConfig.load(stated)
    assert speed_of_sound_note(config, load_protocol(shipped)) == ""
    assert config.speed_of_sound_for(1, 1480.0, test_object=True) == 1480.0
    assert config.speed_of_sound_for(1, 1480.0) == 1540.0
    assert BenchConfig.load(per_channel).speed_of_sound_for(1, 1480.0, test_object=True) == 1480
    assert BenchConfig.load(per_channel).speed_of_sound_for(1, 1480.0) == 1490
    phasors = {}
    for name, bench in (("plain", plain), ("stated", stated), ("channel", per_channel)):
        out = tmp_path / f"{name}.h5"
        assert _run(shipped, bench, out).status == "completed"
        used, _ = _used(out)
        assert used == {"ch1": {1480.0}}, (name, used)
        with SessionReader(out) as reader:
            phasors[name] = np.array([ch.phasor_m for step in reader.steps(with_echoes=False)
                                      for ch in step.channels])
    for name in ("stated", "channel"):
        np.testing.assert_allclose(np.abs(phasors[name]), np.abs(phasors["plain"]), rtol=1e-9)
