"""Windows where a stop or a failure used to be lost or misrecorded (review, session 50):
a ``kill -INT`` while ``run`` opened the bench and the file, with SIGINT inherited as
ignored, was ignored and the whole protocol ran; a resume that failed after recording its
run left that run "running" ("a killed run may have left an output on")."""

from __future__ import annotations

import os
import signal
import time

import pytest

from pelvislab.acquisition import runner as runner_module
from pelvislab.acquisition.session import SessionReader, SessionWriter
from pelvislab.app.cli import main
from pelvislab.tests.test_runner_aiming import PROTOCOL as AIM_PROTOCOL

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")

PROTOCOL = AIM_PROTOCOL.split("[[setups]]\nname = \"b\"")[0]  # three steps, two channels


def _completed_session(tmp_path):
    """A 3-step session run to its end on the simulated bench: (protocol, file)."""
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    with runner_module.prepare_session(protocol, out, bench=sim_bench.open_simulated_bench(
            generators="python")) as session:
        assert session.run().status == "completed"
    return protocol, out


def test_sigint_inherited_as_ignored_stops_run_while_it_prepares(tmp_path, monkeypatch,
                                                                 capsys):
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    original = runner_module.prepare_session

    def prepare_then_signal(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # as `kill -INT` from the script that started it
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:  # the handler runs between bytecodes
            time.sleep(0.01)
        return original(*args, **kwargs)

    monkeypatch.setattr(runner_module, "prepare_session", prepare_then_signal)
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job's SIGINT
    try:
        code = main(["run", str(protocol), "--out", str(out), "--quiet"])
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # put back as it was
    finally:
        signal.signal(signal.SIGINT, before)
    assert code == 130, capsys.readouterr().err
    assert "interrupted by SIGINT" in capsys.readouterr().err
    assert not out.exists()  # stopped before the file: nothing measured


def test_a_resume_that_fails_before_its_first_step_records_how_its_run_ended(tmp_path,
                                                                            monkeypatch):
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    with runner_module.prepare_session(protocol, out, bench=sim_bench.open_simulated_bench(
            generators="python")) as session:
        session.runner.abort("stopped by the test", "aborted")  # before any step
        session.run()

    def failing_repair(self):
        raise OSError("Can't synchronously write data (addr overflow)")

    monkeypatch.setattr(SessionWriter, "repair_frf", failing_repair)
    with pytest.raises(OSError, match="addr overflow"):
        runner_module.prepare_session(protocol, out, resume=True,
                                      bench=sim_bench.open_simulated_bench(generators="python"))
    with SessionReader(out) as reader:
        status, reason = reader.status
        runs = [dict(g.attrs) for _, g in sorted(reader.handle["runs"].items())]
    assert len(runs) == 2
    assert status == "failed" and "before the first step" in reason, (status, reason)
    assert "addr overflow" in reason
    assert "ended_utc" in runs[-1]


def _damage_object_header(path, name: str) -> None:
    """Overwrite the version byte of object ``name``'s header, as a kill inside the flush
    that wrote it can leave it ("bad object header version number")."""
    import h5py

    with h5py.File(path, "r") as h5:
        address = h5py.h5o.get_info(h5[name].id).addr
    with open(path, "r+b") as f:
        f.seek(address)
        f.write(b"\xff")


@pytest.fixture
def damaged_run_record(tmp_path):
    protocol, out = _completed_session(tmp_path)
    _damage_object_header(out, "runs/000")
    return protocol, out


def test_a_damaged_run_record_leaves_the_session_readable(damaged_run_record, tmp_path,
                                                          capsys):
    """A kill -9 while a run's record was flushed (as it started or ended) left that group
    unreadable, and session info, --resume, identify and reprocess all refused the file
    ("Unable to synchronously open object"), its steps and /frf whole (review, session 50)."""
    from pelvislab.acquisition.session import run_records
    from pelvislab.app.commands._common import incomplete_session_warning
    from pelvislab.app.commands.identify import recorded_calibration_std

    protocol, out = damaged_run_record
    with SessionReader(out) as reader:
        (name, attrs, problem), = run_records(reader.handle)
        assert attrs is None and "run 000 is unreadable" in problem
        status, reason = reader.status
        assert status == "damaged" and reason == problem
        assert reader.outputs_confirmed_off is None
        assert len(list(reader.steps(with_echoes=False))) == 3
    assert main(["session", "info", str(out)]) == 0
    captured = capsys.readouterr()
    assert "run 000 is unreadable" in captured.out + captured.err
    assert "steps: 3 acquired of 3 planned" in captured.out
    assert "damaged" in incomplete_session_warning(out)
    recorded_calibration_std(out, [40.0])  # the bench record of the latest readable run
    assert main(["reprocess", str(out), "--out", str(tmp_path / "r.h5")]) == 0
    with SessionReader(tmp_path / "r.h5") as reader:
        assert any("run 000 not copied" in line for line in reader.log_lines())
        assert len(list(reader.steps(with_echoes=False))) == 3
    capsys.readouterr()
    assert main(["run", str(protocol), "--out", str(out), "--resume"]) == 0
    assert "nothing to measure" in capsys.readouterr().err


def test_a_log_chunk_lost_to_a_kill_is_salvaged_and_a_resume_goes_on(damaged_run_record,
                                                                      tmp_path):
    """A kill while ``/log`` grew into a new chunk left that chunk's address past the end of
    allocation the superblock recorded: reading the log gave one error line for all of it,
    and every resume failed writing its first log line ("addr overflow"; review, session
    50). Simulated here: a second chunk, then the recorded end set inside it and the file
    cut there, as the kill left it. The readable lines are kept, the resume writes on."""
    import struct

    import h5py

    protocol, out = damaged_run_record
    path = tmp_path / "log.h5"
    with h5py.File(out, "r") as src, h5py.File(path, "w", libver=("earliest", "v110")) as h5:
        for name in ("protocol", "bench", "steps", "frf", "log"):
            src.copy(src[name], h5, name=name)
        for key, value in src.attrs.items():
            h5.attrs[key] = value
        h5.create_group("runs").create_group("000").attrs["status"] = "running"  # killed
    writer = SessionWriter.resume(path)
    first = len(writer.handle["log"])
    for k in range(300):
        writer.log(f"line {k}")
    writer.close()
    with h5py.File(path, "r") as h5:
        log = h5["log"]
        assert log.id.get_num_chunks() == 2
        lost_chunk = log.id.get_chunk_info(1).byte_offset
    with open(path, "r+b") as f:
        assert f.read(9)[8] == 0  # superblock version 0: end of allocation at byte 40
        f.seek(40)
        f.write(struct.pack("<Q", lost_chunk + 1000))
    os.truncate(path, lost_chunk + 1000)

    with SessionReader(path) as reader:
        lines = reader.log_lines()
    assert lines[first:256] == [line for line in lines[first:256] if " INFO line " in line]
    assert len(lines) == 257 and "unreadable" in lines[-1], lines[-1]
    writer = SessionWriter.resume(path)  # failed: addr overflow at its first log line
    writer.log("after the kill")
    writer.close()
    with SessionReader(path) as reader:
        lines = reader.log_lines()
        assert len(list(reader.steps(with_echoes=False))) == 3
    # the salvaged lines, the warning, the reserve after a killed run, the new line
    assert len(lines) == 259 and lines[-1].endswith("INFO after the kill")
    assert "the session log was damaged" in lines[-3] and "WARNING" in lines[-3]
    assert "reserved past the file's recorded end" in lines[-2]
    assert lines[first].endswith("INFO line 0")


def test_output_names_the_review_found_misreported(tmp_path, capsys):
    """A legal 250-byte --out was refused ("[Errno 36] File name too long" on the hidden
    temporary name); --out "" read ". is a folder" (review, session 50)."""
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    long_name = tmp_path / ("a" * 247 + ".h5")
    assert main(["run", str(protocol), "--out", str(long_name), "--quiet"]) == 0
    with SessionReader(long_name) as reader:
        assert reader.status[0] == "completed"
    capsys.readouterr()
    assert main(["run", str(protocol), "--out", "", "--quiet"]) == 1
    assert "name is empty" in capsys.readouterr().err


def test_a_file_size_limit_is_checked_like_free_space(tmp_path):
    """A file-size limit (``ulimit -f``) failed a write part way: exit 139 (a segmentation
    fault inside HDF5's flush or close) after pages of h5py tracebacks, and a file HDF5
    refused whole ("truncated file"; review, session 50). The limit is now checked as the
    free disk space is: too small to start, refused before anything is written."""
    import resource
    import subprocess
    import sys

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"

    def limit_file_size() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (1_600_000, resource.RLIM_INFINITY))

    done = subprocess.run([sys.executable, "-m", "pelvislab.app", "run", str(protocol),
                           "--out", str(out), "--quiet"], preexec_fn=limit_file_size,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, (done.returncode, done.stderr[-2000:])
    assert "file-size limit (ulimit -f)" in done.stderr and "Traceback" not in done.stderr
    assert not out.exists() and not list(tmp_path.glob(".s.h5.*"))


INJECT_WRITE_FAILURE = """
import errno, sys
from pelvislab.acquisition import session
original = session.SessionWriter.append_step.__wrapped__
calls = []
def failing(self, step):
    calls.append(1)
    if len(calls) == 2:  # HDF5 refusing the second step's write
        raise OSError(errno.EIO, "Driver write request failed (errno = 5, "
                      "error message = 'Input/output error')")
    return original(self, step)
session.SessionWriter.append_step = session._write_guarded(failing)
from pelvislab.app.cli import main
sys.argv[1:] = {argv!r}
sys.exit(main())
"""


def test_a_write_refused_part_way_ends_the_run_in_one_line_and_it_resumes(tmp_path):
    """An error no check foresees (an I/O error, a quota, a disk filled by another process)
    while a step is written: one reason, exit 3, no traceback, the process not crashed;
    the complete step before it is kept and --resume completes the plan."""
    import subprocess
    import sys

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    argv = ["run", str(protocol), "--out", str(out), "--quiet"]
    done = subprocess.run([sys.executable, "-c", INJECT_WRITE_FAILURE.format(argv=argv)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 3, (done.returncode, done.stderr[-2000:])
    assert "Traceback" not in done.stderr, done.stderr[-2000:]
    last = done.stderr.strip().splitlines()[-1]
    assert "Input/output error" in last and "--resume" in last, last
    assert main(["run", str(protocol), "--out", str(out), "--resume", "--quiet"]) == 0
    with SessionReader(out) as reader:
        assert reader.status[0] == "completed"
        steps = list(reader.steps(with_echoes=False))
        assert len(steps) == 3 == len({s.key for s in steps})
        assert any("reserved past the file's recorded end" in line
                   for line in reader.log_lines())


def test_a_file_cut_short_of_its_recorded_end_is_extended_by_resume(damaged_run_record):
    """What a write refused part way leaves: the superblock records an end the data never
    reached, and HDF5 refused the whole file ("truncated file"). session info says how far
    short and what to do; --resume extends it (a hole) and goes on. A file far shorter than
    its recorded end (a copy cut short, a damaged superblock: 2**40 made a 1 TiB file) is
    refused and left as it is."""
    import struct

    from pelvislab.acquisition.session import SessionFileError

    protocol, out = damaged_run_record
    size = out.stat().st_size
    os.truncate(out, size - 500)
    with pytest.raises(SessionFileError, match="ends 500 bytes before the end"):
        SessionReader(out)
    assert main(["run", str(protocol), "--out", str(out), "--resume", "--quiet"]) == 0
    assert out.stat().st_size >= size
    with SessionReader(out) as reader:
        assert len({s.key for s in reader.steps(with_echoes=False)}) == 3
        assert any("extended to" in line for line in reader.log_lines())
    far = out.with_name("far.h5")
    far.write_bytes(out.read_bytes())
    with open(far, "r+b") as f:
        f.seek(40)
        f.write(struct.pack("<Q", 2**40))
    before = far.stat().st_size
    assert main(["run", str(protocol), "--out", str(far), "--resume", "--quiet"]) == 1
    assert far.stat().st_size == before


def test_session_info_check_reads_every_step_whole(tmp_path, capsys):
    """The summary reads the steps' attributes only: a step whose echoes cannot be read
    passed as "3 acquired of 3 planned" (review, session 50). --check reads every step's
    data, names the damaged group and exits 1."""
    protocol, out = _completed_session(tmp_path)
    assert main(["session", "info", str(out), "--check"]) == 0
    assert "check: 3 step group(s) read whole, none damaged" in capsys.readouterr().out
    _damage_object_header(out, "steps/000001/echoes/ch1")
    assert main(["session", "info", str(out)]) == 0  # attributes only: looks complete
    assert "3 acquired of 3 planned" in capsys.readouterr().out
    assert main(["session", "info", str(out), "--check"]) == 1
    text = capsys.readouterr().out
    assert "1 damaged:" in text and "000001" in text, text


def test_a_link_left_at_the_recorded_end_by_a_kill_never_reads_new_objects(tmp_path):
    """A kill inside a step's flush can leave its link written and its group not, pointing
    at the end of allocation the superblock recorded (a review, session 50: steps/000001 at
    exactly the old end), where the resume allocates from. Simulated: the last step's group
    cut off at its own address (which here damages the run record and the step before it
    too). The resume reserves past the end, logs it, measures the damaged steps again and
    reads no step twice. (This simulation does not put a new object at the damaged
    address without the reserve either: it checks the resume, not the overlap itself.)"""
    import struct

    import h5py

    protocol, out = _completed_session(tmp_path)
    with h5py.File(out, "r+") as h5:
        h5["runs/000"].attrs["status"] = "running"  # killed
        last = sorted(h5["steps"])[-1]
        address = h5py.h5o.get_info(h5["steps"][last].id).addr
    with open(out, "r+b") as f:
        f.seek(40)
        f.write(struct.pack("<Q", address))
    os.truncate(out, address)
    assert main(["run", str(protocol), "--out", str(out), "--resume", "--quiet"]) == 0
    with SessionReader(out) as reader:
        steps = list(reader.steps(include_incomplete=True, with_echoes=False))
        assert any(d.startswith(last) for d in reader.damaged), reader.damaged
        assert [s.index for s in steps if f"{s.index:06d}" == last] == []
        assert len(steps) == 3 == len({s.key for s in steps})
