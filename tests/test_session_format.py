"""Session files (design 4.2): layout, round trip, never overwrite, damaged/foreign files."""

from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np
import pytest

from pelvislab.acquisition.frfset import read_frf, write_frf
from pelvislab.acquisition.protocol import Point, parse_protocol
from pelvislab.acquisition.session import (
    ChannelData,
    SessionFileError,
    SessionReader,
    SessionWriter,
    StepData,
    frf_from_steps,
)
from pelvislab.app.cli import main

POINTS = {
    "a": Point("a", "sacrum", (-0.15, 0.0, -0.05), (-1.0, 0.0, 0.0)),
    "b": Point("b", "innominate_left", (0.0, 0.11, 0.0), (1.0, 0.0, 0.0)),
    "c": Point("c", "innominate_right", (0.0, -0.11, 0.0), (1.0, 0.0, 0.0)),
}
TEXT = """
schema = "pelvislab-protocol"
schema_version = 1
name = "session-test"
[sweep]
frequencies_hz = [80.0, 180.0, 280.0]
drive_vpp = 0.5
[ultrasound]
pulses = 400
samples = 64
[[setups]]
name = "s1"
excitation = "a"
transducers = { ch1 = "a", ch2 = "b" }
[[setups]]
name = "s2"
excitation = "c"
transducers = { ch1 = "b" }
"""
BENCH = {"simulated": True, "name": "test", "drive": {"identity": "gen", "resource": "SIM::1"}}


@pytest.fixture
def protocol():
    return parse_protocol(TEXT, "t.toml", None, POINTS)


def make_step(protocol, setup_index: int, f: float, rng: np.random.Generator) -> StepData:
    setup = protocol.setups[setup_index]
    chans = []
    for ch, name in sorted(setup.transducers.items()):
        chans.append(ChannelData(
            f"ch{ch}", rng.integers(-128, 127, (400, 64), dtype=np.int8),
            rng.uniform(-2e-9, 0, 400), 500e6, 5000.0, 10e-6, 0.004, 0.0, 1540.0,
            protocol.points[name], rng.normal(size=400) * 1e-6,
            complex(*rng.normal(size=2)) * 1e-6, 1e-9, {"ok": True, "lost_fraction": 0.0}))
    return StepData(setup.name, f, protocol.points[setup.excitation], 1.0, chans, 2.0 - 1j,
                    0.5, extra={"plan_index": 0})


def write_session(path, protocol, n_steps: int) -> list[StepData]:
    rng = np.random.default_rng(1)
    steps = []
    with SessionWriter.create(path, protocol, BENCH, "test") as w:
        w.start_run(BENCH)
        for k in range(n_steps):
            step = make_step(protocol, k // 3, protocol.sweep.frequencies_hz[k % 3], rng)
            w.append_step(step)
            w.log(f"step {k}")
            steps.append(step)
        w.finish_run("completed", "", {"drive": [(1.0, "OUTP ON"), (2.5, "OUTP OFF")]})
    return steps


def test_layout_matches_design_4_2(tmp_path, protocol):
    path = tmp_path / "s.h5"
    write_session(path, protocol, 4)
    with h5py.File(path, "r") as f:
        assert f.attrs["schema"] == "pelvislab-session" and f.attrs["schema_version"] == 1
        for key in ("created_utc", "software_version"):
            assert key in f.attrs
        assert "toml" in f["protocol"].attrs and f["bench"].attrs["simulated"]
        assert sorted(f["steps"]) == ["000000", "000001", "000002", "000003"]
        s = f["steps/000000"]
        for key in ("setup", "frequency_hz", "input", "started_at_s", "status"):
            assert key in s.attrs
        echo = s["echoes/ch1"]
        assert echo.dtype == np.int8 and echo.shape == (400, 64)
        assert echo.compression == "gzip"
        for key in ("sample_rate_hz", "prf_hz", "delay_s", "volts_per_count", "volts_offset",
                    "speed_of_sound_m_s", "output"):
            assert key in echo.attrs
        assert s["echoes/ch1_trigger_offset_s"].dtype == np.float64
        assert s["displacement/ch1"].shape == (400,)
        assert s["phasor/ch1"].dtype == np.complex128 and s["phasor/ch1"].shape == ()
        assert s["force_phasor_n"].dtype == np.complex128
        assert f["frf"].attrs["units"] == "m/N"
        assert len(f["log"]) == 4


def test_round_trip_and_frf(tmp_path, protocol):
    path = tmp_path / "s.h5"
    steps = write_session(path, protocol, 4)
    with SessionReader(path) as r:
        back = list(r.steps())
        assert r.status == ("completed", "")
        assert [s.key for s in back] == [s.key for s in steps]
        np.testing.assert_array_equal(back[2].channels[1].codes, steps[2].channels[1].codes)
        assert back[0].channels[0].phasor_m == steps[0].channels[0].phasor_m
        assert back[0].input == steps[0].input
        assert back[0].channels[1].output == protocol.points["b"]
    frf = read_frf(path)  # the /frf contract, readable by every consumer
    assert frf.H.shape == (3, 2, 2)  # frequencies x outputs (a, b) x inputs (a, c)
    assert np.isfinite(frf.H).sum() == 2 * 3 + 1  # setup s1 all 3 f x 2 ch; s2 one step
    again = frf_from_steps(steps, list(frf.frequency_hz), frf.outputs, frf.inputs)
    np.testing.assert_allclose(again.H, frf.H)
    h = steps[1].channels[0].phasor_m / steps[1].force_phasor_n
    assert frf.H[1, 0, 0] == pytest.approx(h)


def test_never_overwrites(tmp_path, protocol):
    path = tmp_path / "s.h5"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError):
        SessionWriter.create(path, protocol, BENCH)
    assert path.read_bytes() == b"precious"


def test_resume_appends_and_checks_protocol(tmp_path, protocol):
    path = tmp_path / "s.h5"
    write_session(path, protocol, 2)
    with pytest.raises(SessionFileError, match="differs"):
        SessionWriter.resume(path, TEXT + "\n# changed\n")
    rng = np.random.default_rng(2)
    with SessionWriter.resume(path, TEXT) as w:
        w.start_run(BENCH)
        assert w.append_step(make_step(protocol, 0, 280.0, rng)) == 2
        w.finish_run("completed")
    with SessionReader(path) as r:
        assert len(list(r.steps())) == 3 and len(r.handle["runs"]) == 2


def test_incomplete_step_is_skipped(tmp_path, protocol):
    path = tmp_path / "s.h5"
    write_session(path, protocol, 3)
    with h5py.File(path, "r+") as f:
        del f["steps/000002"].attrs["status"]  # as if killed before the last attribute
        g = f["steps"].create_group("000003")  # and a group with nothing in it
        g.attrs["setup"] = "s1"
    with SessionReader(path) as r:
        assert len(list(r.steps())) == 2
        assert len(r.incomplete) + len(r.damaged) == 2


def test_truncated_file_gives_one_line_error(tmp_path, protocol):
    path = tmp_path / "s.h5"
    write_session(path, protocol, 3)
    data = path.read_bytes()
    for cut in (10, 600, len(data) // 2):
        bad = tmp_path / f"cut{cut}.h5"
        bad.write_bytes(data[:cut])
        with pytest.raises(SessionFileError) as info:
            SessionReader(bad)
        assert "\n" not in str(info.value) and str(bad) in str(info.value)


def test_wrong_schema_and_version(tmp_path, protocol):
    path = tmp_path / "s.h5"
    write_session(path, protocol, 1)
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = 2
    with pytest.raises(SessionFileError, match="schema_version 2"):
        SessionReader(path)
    frf_only = tmp_path / "frf.h5"
    write_frf(frf_only, read_frf(path))
    with pytest.raises(SessionFileError, match="FRF-only"):
        SessionReader(frf_only)
    foreign = tmp_path / "other.h5"  # another program's HDF5 file (GUI review, session 35:
    with h5py.File(foreign, "w") as f:  # "has schema '', expected 'pelvislab-session'")
        f["data"] = [1.0, 2.0]
    with pytest.raises(SessionFileError, match="an HDF5 file but not a pelvislab session"):
        SessionReader(foreign)


def test_cli_resume_and_reprocess_refuse_bad_files(tmp_path, protocol):
    garbage = tmp_path / "g.h5"
    garbage.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    proto = tmp_path / "p.toml"
    proto.write_text(TEXT.replace('name = "session-test"', 'name = "x"') + """
[points.a]
bone = "sacrum"
position_m = [-0.15, 0.0, -0.05]
direction = [-1.0, 0.0, 0.0]
[points.b]
bone = "innominate_left"
position_m = [0.0, 0.11, 0.0]
direction = [1.0, 0.0, 0.0]
[points.c]
bone = "innominate_right"
position_m = [0.0, -0.11, 0.0]
direction = [1.0, 0.0, 0.0]
""")
    before = garbage.read_bytes()
    for argv in (["run", str(proto), "--out", str(garbage), "--resume"],
                 ["run", str(proto), "--out", str(garbage)],
                 ["reprocess", str(garbage), "--out", str(tmp_path / "o.h5")]):
        proc = subprocess.run([sys.executable, "-m", "pelvislab.app", *argv],
                              capture_output=True, text=True)
        assert proc.returncode == 1, proc.stderr
        lines = [ln for ln in proc.stderr.strip().splitlines() if not ln.startswith("warning:")]
        assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert garbage.read_bytes() == before
    assert not (tmp_path / "o.h5").exists()


def test_reprocess_refuses_existing_output(tmp_path, protocol):
    path = tmp_path / "s.h5"
    write_session(path, protocol, 1)
    out = tmp_path / "o.h5"
    out.write_bytes(b"keep")
    assert main(["reprocess", str(path), "--out", str(out)]) == 1
    assert out.read_bytes() == b"keep"


# --------------------------------------------------------------------------- corrupted files
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_CORRUPT_SOURCE: dict[str, bytes] = {}


def _valid_bytes(tmp_path_factory) -> bytes:
    if "data" not in _CORRUPT_SOURCE:
        path = tmp_path_factory.mktemp("src") / "s.h5"
        write_session(path, parse_protocol(TEXT, "t.toml", None, POINTS), 3)
        _CORRUPT_SOURCE["data"] = path.read_bytes()
    return _CORRUPT_SOURCE["data"]


@settings(max_examples=25, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.floats(0, 1), st.binary(min_size=1, max_size=16)),
                min_size=1, max_size=4),
       st.one_of(st.none(), st.floats(0.05, 1.0)))
def test_corrupted_files_give_one_line_errors_or_readable_steps(tmp_path_factory, patches, keep):
    data = bytearray(_valid_bytes(tmp_path_factory))
    for where, junk in patches:
        at = int(where * (len(data) - len(junk)))
        data[at:at + len(junk)] = junk
    if keep is not None:
        data = data[: int(keep * len(data))]
    path = tmp_path_factory.mktemp("bad") / "bad.h5"
    path.write_bytes(bytes(data))
    try:
        reader = SessionReader(path)
    except SessionFileError as exc:
        assert "\n" not in str(exc)
        return
    with reader:
        steps = list(reader.steps())  # damaged groups are reported, not raised
        assert len(steps) + len(reader.damaged) + len(reader.incomplete) <= 3
        reader.log_lines()
        try:
            reader.frf()
        except ValueError as exc:  # FrfFileError / SessionFileError, one line
            assert "\n" not in str(exc)


def test_a_channel_whose_tracking_failed_keeps_its_quality(tmp_path, protocol):
    # review, session 38: a channel without displacement (its tracking failed) had its
    # quality stored nowhere: why it failed, and the gate the operator set, were lost
    path = tmp_path / "s.h5"
    rng = np.random.default_rng(2)
    step = make_step(protocol, 0, 80.0, rng)
    failed = step.channels[1]
    failed.displacement_m, failed.phasor_m, failed.phasor_std_m = None, None, None
    failed.quality = {"ok": False, "message": "tracking failed: the gate (30, 50) of the "
                      "first echoes is flat", "gate_source": "operator", "gate_start": 30,
                      "gate_stop": 50}
    with SessionWriter.create(path, protocol, BENCH, "test") as w:
        w.start_run(BENCH)
        w.append_step(step)
        w.finish_run("completed", "", {})
    with SessionReader(path) as reader:
        back = {c.name: c for c in next(iter(reader.steps())).channels}
    assert back["ch2"].displacement_m is None
    assert back["ch2"].quality["message"].startswith("tracking failed: the gate (30, 50)")
    assert back["ch2"].quality["gate_source"] == "operator"
    assert back["ch1"].quality["ok"]  # the other channel's, with its displacement
