"""HDF5 session files, schema ``pelvislab-session`` version 1 (design 4.2).

Writer and reader of the one session file layout; ``docs/session-format.md`` documents every
group and attribute. What makes a file survive ``kill -9`` at any moment:

- one group per step under ``/steps``, written completely (raw echoes gzip-compressed,
  displacement, phasors, ``status="complete"`` set last) and then the file is flushed: a
  step is written once and never touched again;
- ``/frf`` is laid out once for the whole plan (every frequency, output and input of the
  protocol, NaN where not measured, via :func:`pelvislab.acquisition.frfset.write_frf`) and
  each new line is then written in place, so no metadata of a finished step is rewritten;
- the session log (``/log``) is a resizable string dataset, appended with each step;
- ``/steps`` and ``/runs`` keep their links in a header sized at creation
  (:func:`_presized_group`), so adding a step never moves them (a kill inside that flush
  made ``/steps`` unreadable);
- nothing is ever written over an existing file: ``create`` refuses an existing path, and
  resuming only appends.

Readers skip any step group whose ``status`` is not ``complete`` (a step cut short) and
report damaged groups instead of failing on them.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import math
import os
import re
import shutil
import socket
import time
import weakref
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from pelvislab.acquisition.frfset import Channels, FrfSet, read_frf_group, write_frf
from pelvislab.acquisition.protocol import Point, Protocol

log = logging.getLogger(__name__)

__all__ = [
    "SESSION_SCHEMA",
    "SESSION_SCHEMA_VERSION",
    "ChannelData",
    "SessionFileError",
    "SessionReader",
    "SessionWriter",
    "StepData",
    "frf_from_steps",
    "plan_channels",
    "remove_stale_partials",
]

SESSION_SCHEMA = "pelvislab-session"
SESSION_SCHEMA_VERSION = 1
STATUS_COMPLETE = "complete"
STATUS_FAILED = "failed"
STATUS_COMPLETE_ALIASES = frozenset({"complete", "completed", "done", "ok", "finished"})
"""Step ``status`` values read as complete: design 4.2 names the attribute, not its values
(this writer's is "complete"; a file written from the design alone with "completed" had
every step skipped: contract audit, session 40)."""
ECHO_COMPRESSION = {"compression": "gzip", "compression_opts": 1}
"""Raw echoes: gzip level 1 (measured on simulated 8-bit echoes: 74 % of the raw size at
~60 ns/sample; level 4 + shuffle was slower and larger for 1-byte codes)."""


class SessionFileError(ValueError):
    """Not a usable session file; the one-line message says which file and why.

    ``schema``: the root ``schema`` attribute found when that is the reason ("" for none:
    another program's HDF5 file, or an FRF-only file with its schema on ``/frf``), else
    None."""

    def __init__(self, message: str, *, schema: str | None = None) -> None:
        super().__init__(message)
        self.schema = schema


SUBJECT_ID_PATTERN = re.compile(r"[A-Za-z0-9._-]{0,32}")


def first_difference(stored: str, given: str) -> str:
    """Where two protocol texts first differ, as "line N: 'stored' in the session, 'given'
    in the file" (a resume refused "differs" without saying where; a comment edited counts:
    the session keeps the very text it was measured with; review, session 50)."""
    a, b = stored.splitlines(), given.splitlines()
    for n, (x, y) in enumerate(zip(a, b, strict=False), start=1):
        if x != y:
            # stripped only where that keeps them different (trailing blanks otherwise)
            a_, b_ = (x.strip(), y.strip()) if x.strip() != y.strip() else (x, y)
            return f"line {n}: {a_[:80]!r} in the session, {b_[:80]!r} in the file"
    if len(a) != len(b):
        n = min(len(a), len(b)) + 1
        longer = "session" if len(a) > len(b) else "file"
        line = (a if len(a) > len(b) else b)[n - 1]
        return f"line {n}: {line.strip()[:80]!r} only in the {longer}"
    return "line endings or trailing whitespace"


def check_subject_id(subject_id: str) -> str:
    """A pseudonymous subject ID: letters, digits, ``-_.``, at most 32 characters (an ID,
    never a name: no spaces)."""
    if not isinstance(subject_id, str) or not SUBJECT_ID_PATTERN.fullmatch(subject_id):
        raise ValueError(f"subject id {subject_id!r}: use letters, digits, '-', '_', '.' only, "
                         "at most 32 characters (a pseudonymous ID, never a name)")
    return subject_id


LOG_LINE_BYTES = 400
"""Session log lines are fixed-length UTF-8 strings (longer lines are cut): unlike
variable-length strings they need no global heap, whose on-disk state a kill -9 can leave
behind the log's own chunks (measured: "bad heap index" when resuming such a file)."""


COMMAND_BYTES = 200
"""Instrument commands in ``/runs/<k>/command_logs`` are stored cut to this many bytes."""


def create_log(group: h5py.Group, lines: Sequence[str] = ()) -> h5py.Dataset:
    """The ``/log`` dataset: resizable, fixed-length UTF-8 lines."""
    data = np.array([log_entry(line) for line in lines], dtype=f"S{LOG_LINE_BYTES}")
    return group.create_dataset("log", data=data, maxshape=(None,), chunks=(256,),
                                dtype=f"S{LOG_LINE_BYTES}")


def _end_of_file_field(path: Path | str) -> int | None:
    """Byte offset of the end-of-allocation address in a version 0 or 1 superblock with
    8-byte addresses, or None for another layout (our files have version 0)."""
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError:
        return None
    if len(head) < 56 or head[:8] != b"\x89HDF\r\n\x1a\n" or head[8] not in (0, 1) \
            or head[13] != 8:
        return None
    return 40 if head[8] == 0 else 44  # version 1 has 4 bytes more before the addresses


def recorded_end_of_file(path: Path | str) -> int | None:
    """The end of allocation a version 0 or 1 superblock records (bytes: what HDF5 checks
    the file's size against), or None for another layout (our files have version 0)."""
    at = _end_of_file_field(path)
    if at is None:
        return None
    with open(path, "rb") as f:
        f.seek(at)
        return int.from_bytes(f.read(8), "little")


CUT_EXTENSION_MAX_BYTES = 64 * 2**20
"""The most :func:`extend_cut_session` adds (and never more than the file's own size)."""


def extend_cut_session(path: Path | str) -> str:
    """Extend a session file that ends before the end its superblock records, with a hole
    (zeros; no disk space used), so that it opens again; a note saying so, or "".

    A write that failed part way (a file-size limit, a quota, a disk filled between the
    free-space check and the flush) left the superblock written with the new end and the
    data beyond the limit not: HDF5 then refused the whole file ("truncated file: eof =
    3072000, stored_eof = 3329205"; review, session 50), its complete steps with it. Only
    what was never written is missing; the objects there read as damaged. Called by
    ``run --resume``; readers only say how to do it (:class:`SessionReader`)."""
    path = Path(path)
    end = recorded_end_of_file(path)
    size = path.stat().st_size
    if end is None or size >= end:
        return ""
    if end - size > min(size, CUT_EXTENSION_MAX_BYTES):
        # not what a failed flush leaves (it lacks at most the flush's bytes): a copy cut
        # short, or a superblock that is itself damaged (an end of 1 TiB made the file
        # 1 TiB; review, session 50)
        raise SessionFileError(f"{path} ends {end - size} bytes before the end its "
                               f"superblock records ({end}): more than a failed write leaves;"
                               " not extended (a copy cut short? copy it again)")
    import fcntl

    with open(path, "r+b") as f:
        try:  # HDF5's own lock: a process writing it now
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise SessionFileError(f"{path} is in use by another process; not "
                                   "extended") from None
        try:
            f.truncate(end)
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    return (f"the file ended {end - size} bytes before the end its superblock records (a "
            f"write that failed part way): extended to {end} bytes with zeros; what was "
            "being written then is lost and reads as damaged")


def _reserve_past_recorded_end(path: Path, n_steps: int) -> str:
    """After a killed run, move the end of allocation the superblock records past what the
    killed flush may have allocated, before HDF5 opens the file; a log line ("" when the
    layout is not known).

    A kill -9 inside a flush can leave links pointing at or past the recorded end (a
    helper's review, session 50: ``steps/000001`` at exactly the old end). The resumed run
    allocates from that end, and its first new object could then sit where the damaged link
    points: the step would read as another object (a new step: a duplicate). Reserved:
    twice the mean step's bytes, at least 1 MB, at most :data:`CUT_EXTENSION_MAX_BYTES`;
    the file is extended to it with a hole (no disk space used on Linux file systems)."""
    at = _end_of_file_field(path)
    end = recorded_end_of_file(path)
    if at is None or end is None:
        return ""
    size = path.stat().st_size
    mean_step = size / max(n_steps, 1)
    reserve = int(min(CUT_EXTENSION_MAX_BYTES, max(2**20, 2 * mean_step)))
    new_end = max(end, size) + reserve
    room = file_size_limit_room(path)
    if room is not None and new_end - size > room:
        return ""  # the step's own space check says what to do
    with open(path, "r+b") as f:
        f.seek(at)
        f.write(int(new_end).to_bytes(8, "little"))
        f.truncate(new_end)
        f.flush()
        os.fsync(f.fileno())
    return (f"the last run was killed: {reserve} bytes reserved past the file's recorded "
            "end, so that nothing new is written where that run's last flush may have "
            "left references")


def salvage_log(h5: h5py.File) -> tuple[list[str], list[str]]:
    """The lines of ``/log`` that can be read, chunk by chunk, and what could not be read.

    A kill -9 while the log grew into a new chunk can leave that chunk's address beyond
    the end of the file HDF5 recorded: reading the whole log failed, and every line was lost
    to readers, though all but the last chunk's were intact (review, session 50: 256 of
    259 lines readable)."""
    try:
        ds = h5["log"]
        n = int(ds.shape[0])
        step = int(ds.chunks[0]) if ds.chunks else max(n, 1)
    except Exception as exc:
        return [], [f"unreadable ({' '.join(str(exc).split())[:160]})"]
    lines: list[str] = []
    problems: list[str] = []
    for start in range(0, n, step):
        try:
            lines += [_text(v) for v in ds[start:start + step]]
        except Exception as exc:
            problems.append(f"lines {start + 1}-{min(n, start + step)} of {n} unreadable "
                            f"({' '.join(str(exc).split())[:160]})")
    return lines, problems


def log_entry(line: str) -> np.bytes_:
    """``line`` as UTF-8, cut to :data:`LOG_LINE_BYTES` on a character boundary."""
    return _utf8_cut(line, LOG_LINE_BYTES)


def _utf8_cut(text: object, n_bytes: int) -> np.bytes_:
    """``text`` as UTF-8, cut to ``n_bytes`` on a character boundary."""
    raw = str(text).encode("utf-8")[:n_bytes]
    return np.bytes_(raw.decode("utf-8", "ignore").encode("utf-8"))


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def _text(value: Any) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray) and value.shape == ():
        return _text(value[()])
    return str(value)


# --------------------------------------------------------------------------- step data
@dataclass
class ChannelData:
    """One transducer channel of one step: raw record, its tracking and phasor."""

    name: str
    """Channel name in the file, ``ch1``/``ch2``."""
    codes: np.ndarray
    """int8/int16 (n_pulses, n_samples) raw digitizer codes."""
    trigger_offset_s: np.ndarray
    sample_rate_hz: float
    prf_hz: float
    delay_s: float
    volts_per_count: float
    volts_offset: float
    speed_of_sound_m_s: float
    output: Point
    displacement_m: np.ndarray | None = None
    phasor_m: complex | None = None
    """Displacement phasor (m, peak) at the step frequency, time of the first pulse."""
    phasor_std_m: float | None = None
    quality: dict[str, float | bool | str] = field(default_factory=dict)


@dataclass
class StepData:
    """One acquired step (``/steps/<index>``)."""

    setup: str
    frequency_hz: float
    input: Point
    started_at_s: float
    """Since the session was created, s."""
    channels: list[ChannelData]
    force_phasor_n: complex
    drive_vpp: float = 0.0
    status: str = STATUS_COMPLETE
    index: int = -1
    extra: dict[str, Any] = field(default_factory=dict)
    """Further step attributes (plan index, quality summary, failure reason)."""

    @property
    def key(self) -> tuple[str, float, int]:
        """(setup, frequency, repeat) as in :attr:`PlannedStep.key`."""
        return (self.setup, round(float(self.frequency_hz), 9), int(self.extra.get("repeat", 0)))


def plan_channels(protocol: Protocol) -> tuple[list[float], Channels, Channels]:
    """The /frf layout of a protocol: sorted frequencies, outputs, inputs (setup order)."""
    frequencies = sorted(set(protocol.sweep.frequencies_hz))
    out_names: list[str] = []
    in_names: list[str] = []
    for s in protocol.setups:
        for ch in sorted(s.transducers):
            if s.transducers[ch] not in out_names:
                out_names.append(s.transducers[ch])
        if s.excitation not in in_names:
            in_names.append(s.excitation)
    return frequencies, _channels([protocol.points[n] for n in out_names]), \
        _channels([protocol.excitations[n] for n in in_names])


def _channels(points: Sequence[Point]) -> Channels:
    unplaced = [p.name for p in points
                if not (np.all(np.isfinite(p.position_m)) and np.all(np.isfinite(p.direction)))]
    if unplaced:
        # a session written from the design alone names its points only (design 4.2)
        raise ValueError(
            f"point(s) {unplaced} have no position or direction: neither in the steps' "
            "attributes (output_/input_ bone, position_m, direction) nor in the landmark "
            "catalogue (protocols/landmarks.toml)")
    return Channels([p.name for p in points], [p.bone for p in points],
                    np.array([p.position_m for p in points], dtype=float).reshape(-1, 3),
                    np.array([p.direction for p in points], dtype=float).reshape(-1, 3))


def frf_from_steps(steps: Sequence[StepData], frequencies_hz: Sequence[float] | None = None,
                   outputs: Channels | None = None, inputs: Channels | None = None,
                   started: float | None = None) -> FrfSet:
    """The FRF set H = X / F (m/N) of ``steps``; later steps win for a repeated line.

    Without a layout, frequencies/outputs/inputs are those the steps hold (sorted
    frequencies, points in order of appearance). ``H_std`` = phasor std / |F| (the drive
    calibration taken as exact).
    """
    if frequencies_hz is None:
        frequencies_hz = sorted({float(s.frequency_hz) for s in steps})
    if outputs is None or inputs is None:
        outs: dict[str, Point] = {}
        ins: dict[str, Point] = {}
        for s in steps:
            ins.setdefault(s.input.name, s.input)
            for c in s.channels:
                outs.setdefault(c.output.name, c.output)
        outputs = outputs or _channels(list(outs.values()))
        inputs = inputs or _channels(list(ins.values()))
    f = np.asarray(frequencies_hz, dtype=float)
    shape = (f.size, len(outputs), len(inputs))
    H = np.full(shape, np.nan + 1j * np.nan)
    H_std = np.full(shape, np.nan)
    at = np.full(f.size, np.nan)
    lines: dict[tuple[int, int, int], list[tuple[complex, float]]] = {}
    for s in steps:
        if s.status != STATUS_COMPLETE or s.force_phasor_n == 0:
            continue
        i = int(np.argmin(np.abs(f - s.frequency_hz)))
        if abs(f[i] - s.frequency_hz) > 1e-6 * max(1.0, s.frequency_hz):
            continue
        j = inputs.index(s.input.name)
        for c in s.channels:
            if c.phasor_m is None or not _usable(c):
                continue
            o = outputs.index(c.output.name)
            std = np.nan if c.phasor_std_m is None else c.phasor_std_m / abs(s.force_phasor_n)
            lines.setdefault((i, o, j), []).append((c.phasor_m / s.force_phasor_n, std))
            at[i] = s.started_at_s
    for (i, o, j), values in lines.items():
        H[i, o, j], H_std[i, o, j] = combine_lines(values)
    return FrfSet(f, H, outputs, inputs, H_std=H_std, acquired_at_s=at)


def combine_lines(values: Sequence[tuple[complex, float]]) -> tuple[complex, float]:
    """One FRF value from repeated measurements (H, std): inverse-variance mean and its
    standard uncertainty; the plain mean (std NaN) when any std is unknown."""
    h = np.array([v for v, _ in values], dtype=complex)
    s = np.array([e for _, e in values], dtype=float)
    if h.size == 1:
        return complex(h[0]), float(s[0])
    if np.all(np.isfinite(s) & (s > 0)):
        w = 1.0 / s**2
        return complex(np.sum(w * h) / w.sum()), float(1.0 / np.sqrt(w.sum()))
    return complex(h.mean()), float("nan")


def _usable(channel: ChannelData) -> bool:
    """A channel's phasor goes into /frf unless its tracking quality was judged bad
    (``quality['ok']`` False); its raw echoes stay in /steps for reprocessing."""
    ok = channel.quality.get("ok", True)
    return bool(ok) if not isinstance(ok, str) else ok.lower() in ("true", "1")


# --------------------------------------------------------------------------- writer
def _point_attrs(attrs: h5py.AttributeManager, prefix: str, point: Point) -> None:
    attrs[prefix] = point.name
    attrs[f"{prefix}_bone"] = point.bone
    attrs[f"{prefix}_position_m"] = np.asarray(point.position_m, dtype=float)
    attrs[f"{prefix}_direction"] = np.asarray(point.direction, dtype=float)


def _attr_value(value: Any) -> Any:
    if value is None:
        return "none"
    if isinstance(value, Mapping):
        return str(dict(value))
    return value


def _pid_alive(pid: int) -> bool:
    """True when process ``pid`` exists (or we cannot tell: then keep its files)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError, OverflowError):
        return True
    return True


def partial_path(path: Path | str, pid: int | None = None) -> Path:
    """The temporary name a new file at ``path`` is built under: ``.<name>.<pid>.partial``
    in the same folder, with the name shortened (and a hash of it kept) where that would
    pass the file system's 255 bytes: a legal 253-byte ``--out`` was refused with
    "[Errno 36] File name too long", naming the temporary file (review, session 50)."""
    import hashlib

    path = Path(path)
    name = path.name
    suffix = f".{os.getpid() if pid is None else pid}.partial"
    # decided for the longest pid, so that creation and the stale-file clean-up (pid 0)
    # shorten alike (review, session 50: a 242-byte name was shortened for one only)
    if len(f".{name}.{'9' * 10}.partial".encode()) > 255:
        digest = hashlib.sha1(name.encode()).hexdigest()[:12]
        name = name.encode()[:200].decode(errors="ignore") + "~" + digest
    return path.with_name(f".{name}{suffix}")


def remove_stale_partials(path: Path | str) -> list[str]:
    """Delete ``.<name>.<pid>.partial`` files next to ``path`` whose process is gone.

    :meth:`SessionWriter.create` builds a session under that temporary name; a kill during
    creation leaves it behind (never at ``path`` itself). Files of running processes (another
    session being created now) are kept. Returns the removed file names; each removal is
    logged (and written to the new session's log by ``create``).
    """
    path = Path(path)
    removed: list[str] = []
    stem = partial_path(path, 0).name[: -len(".0.partial")]
    pattern = re.compile(rf"{re.escape(stem)}\.(\d+)\.partial")
    try:
        candidates = list(path.parent.iterdir())
    except OSError:
        return removed
    for candidate in candidates:
        match = pattern.fullmatch(candidate.name)
        if match is None or _pid_alive(int(match.group(1))):
            continue
        try:
            candidate.unlink()
        except OSError as exc:
            log.warning("could not remove stale %s: %s", candidate, exc)
            continue
        log.warning("removed stale %s (its process %s is gone)", candidate, match.group(1))
        removed.append(candidate.name)
    return removed


def process_identity(pid: int) -> tuple[str, int] | None:
    """(boot id, start time in clock ticks since boot) of process ``pid`` on this machine,
    from Linux's /proc; None where there is no /proc or no such process. A pid alone says
    nothing once the process has ended: after a reboot (a power cut, the usual end of a
    killed run) or in time, another process holds it; the pair does not repeat."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        stat = Path(f"/proc/{int(pid)}/stat").read_text()
        # "pid (comm) state ppid ...": comm may hold spaces and parentheses; starttime is
        # field 22, the 20th after the comm
        return boot, int(stat[stat.rindex(")") + 2:].split()[19])
    except (OSError, ValueError, IndexError):
        return None


_WRITING: set[str] = set()
"""Session files a :class:`SessionWriter` of this process has open (resolved paths): a run
recorded with this process's identity is being written only if its file is one of them."""

WRITE_FAILURES: list[str] = []
"""Session files this process failed to write (HDF5 refused a write: a file-size limit, a
quota, an I/O error, a disk filled by another process). HDF5 has no way back: such a file
can no longer be flushed or closed, and the library's own clean-up at exit then crashed
the process (segmentation fault, exit 139, after pages of tracebacks; review, session 50).
The command line ends the process without that clean-up when this is not empty
(``pelvislab.app.cli.main``); every complete step was flushed before."""


class SessionWriteError(OSError):
    """Writing the session file failed (see :data:`WRITE_FAILURES`): one line."""


def _fill_new_session(handle: h5py.File, protocol: Protocol, bench: Mapping[str, Any],
                      software_version: str, subject_id: str | None) -> None:
    """Write a new session's layout into ``handle`` (:meth:`SessionWriter.create`) and
    close it (an error leaves it open: the caller closes it without writing)."""
    handle.attrs["schema"] = SESSION_SCHEMA
    handle.attrs["schema_version"] = SESSION_SCHEMA_VERSION
    handle.attrs["created_utc"] = _utc_now()
    handle.attrs["created_unix_s"] = time.time()
    handle.attrs["software_version"] = software_version
    handle.attrs["protocol_name"] = protocol.name
    handle.attrs["subject_id"] = (protocol.subject.id if subject_id is None
                                  else subject_id)
    handle.attrs["subject_position"] = protocol.subject.position
    g = handle.create_group("protocol")
    g.attrs["toml"] = protocol.text
    g.attrs["source"] = protocol.source
    _write_bench(handle.create_group("bench"), bench)
    # every step and run adds a link to these two: sized now, while the file
    # is still private, so that no later flush has to move them
    _presized_group(handle, "steps", 2 * len(protocol.steps()) + 64)
    _presized_group(handle, "runs", 256)
    create_log(handle)
    frequencies, outputs, inputs = plan_channels(protocol)
    shape = (len(frequencies), len(outputs), len(inputs))
    write_frf(handle, FrfSet(frequencies, np.full(shape, np.nan + 1j * np.nan),
                             outputs, inputs, H_std=np.full(shape, np.nan),
                             acquired_at_s=np.full(len(frequencies), np.nan)))
    handle.flush()  # a write refused raises here; inside close() it crashed the process
    handle.close()


def file_size_limit_room(path: Path | str) -> int | None:
    """Bytes the process's file-size limit (``RLIMIT_FSIZE``, ``ulimit -f``) leaves for the
    file at ``path`` to grow, or None without a limit."""
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    except (ImportError, OSError, ValueError):
        return None
    if limit == resource.RLIM_INFINITY or limit < 0:
        return None
    try:
        size = Path(path).stat().st_size
    except OSError:
        size = 0
    return max(0, int(limit) - size)


def _write_failure_reason(exc: BaseException) -> str:
    """The system's reason for a failed HDF5 write ("File too large"), else HDF5's text."""
    errno_ = getattr(exc, "errno", None)
    if errno_:
        return os.strerror(errno_)
    found = re.search(r"error message = '([^']+)'", str(exc))
    return found.group(1) if found else " ".join(str(exc).split())[:160]


def refused_write_text(target: Path | str, exc: BaseException) -> str:
    """The one line for a new file ``target`` whose write ``exc`` refused (the system's
    reason; the caller has removed what it wrote)."""
    return (f"writing {target} failed: {_write_failure_reason(exc)}; nothing was written "
            "under that name")


def _is_write_failure(exc: BaseException) -> bool:
    """Whether ``exc`` is HDF5 failing to write (not, say, a read of a damaged object)."""
    import errno

    if getattr(exc, "errno", None) in (errno.EFBIG, errno.ENOSPC, errno.EIO, errno.EDQUOT,
                                       errno.EROFS):
        return True
    text = str(exc).lower()
    return any(w in text for w in ("write failed", "write request failed", "unable to "
                                   "extend file", "unable to flush", "can't write",
                                   "synchronously write", "synchronously flush"))


def _close_without_writing(handle: h5py.File) -> None:
    """Leave ``handle`` after a failed write without writing to its file again: what the
    file holds is synced, then its descriptor is pointed at /dev/null, so that whatever
    HDF5 still writes (its flush, the superblock with an end the data never reached) goes
    nowhere. The handle stays open."""
    try:
        fd = int(handle.id.get_vfd_handle())
    except Exception as exc:  # no descriptor to redirect: leave the file open
        log.error("%s: not closed after its failed write (%s)", handle.filename, exc)
        return
    try:
        os.fsync(fd)  # the complete steps, flushed before, reach the disk
    except OSError as exc:
        log.error("fsync of %s after a failed write: %s", handle.filename, exc)
    null = os.open(os.devnull, os.O_RDWR)
    try:
        os.dup2(null, fd)
    finally:
        os.close(null)
    # not closed: after a refused write HDF5's flush and close can crash the process
    # (segmentation fault inside close(), measured at a 1 MB file-size limit); the
    # command line ends the process without HDF5's clean-up (WRITE_FAILURES)


def _write_guarded(method: Any) -> Any:
    """Turn an HDF5 write failure in a :class:`SessionWriter` method into one
    :class:`SessionWriteError` naming the file and the system's reason, and remember it."""
    import functools

    @functools.wraps(method)
    def guarded(self: SessionWriter, *args: Any, **kwargs: Any) -> Any:
        if self.write_error is not None:
            raise SessionWriteError(self.write_error)
        try:
            return method(self, *args, **kwargs)
        except (OSError, RuntimeError) as exc:
            if isinstance(exc, SessionWriteError) or not _is_write_failure(exc):
                raise
            reason = _write_failure_reason(exc)
            self.write_error = (f"writing {self.path} failed: {reason}; every complete "
                                "step before it is on disk: remove the cause (free space, "
                                "the file-size limit), then continue with --resume")
            WRITE_FAILURES.append(str(self.path))
            raise SessionWriteError(self.write_error) from None
    return guarded


class WriteRefusedError(OSError):
    """A file that cannot be written: too little free disk or file-size-limit room to
    start it, or a write the system refused. ``WriteRefusedError(errno, text)``; its
    ``str`` is ``text``, the one line the command prints."""

    def __str__(self) -> str:
        return str(self.strerror or super().__str__())


NEW_FILE_MARGIN_BYTES = 64 * 1024
"""Room a new derived file (a reprocessed session) needs beyond 1.25 times its estimated
size before it is started (:func:`new_hdf5_file`): HDF5's own structures."""


@contextlib.contextmanager
def new_hdf5_file(tmp: Path, target: Path, bytes_estimate: int) -> Iterator[h5py.File]:
    """Create the HDF5 file ``tmp`` (to be published as ``target`` by the caller, who also
    removes ``tmp``), yield it, flush and close it.

    Refused before anything is written (:class:`WriteRefusedError`, ENOSPC or EFBIG) when
    the disk or the file-size limit (``ulimit -f``) leaves less than 1.25 times
    ``bytes_estimate`` plus :data:`NEW_FILE_MARGIN_BYTES`. A write refused all the same
    (a disk filled by another process, a quota, an I/O error), also one HDF5 reports only
    while it frees an object (an "unraisable" error: the file would have been published
    with zeros where the data should be; review, session 51), raises
    :class:`SessionWriteError` naming ``target`` and the system's reason; the handle is
    then left without writing to its file again (:func:`_close_without_writing`): HDF5's
    flush and close after a refused write crashed the process (segmentation fault)."""
    import errno
    import sys

    need = int(1.25 * max(0, int(bytes_estimate))) + NEW_FILE_MARGIN_BYTES
    free = shutil.disk_usage(target.parent).free
    if free < need:
        raise WriteRefusedError(errno.ENOSPC, f"cannot write {target}: {free / 2**20:.1f} MB "
                                f"free in {target.parent}, it needs about "
                                f"{need / 2**20:.1f} MB")
    room = file_size_limit_room(tmp)
    if room is not None and room < need:
        raise WriteRefusedError(errno.EFBIG, f"cannot write {target}: the file-size limit "
                                f"(ulimit -f) is {room / 2**20:.2f} MB, it needs about "
                                f"{need / 2**20:.2f} MB; raise it")
    try:
        handle = h5py.File(tmp, "w-")
    except OSError as exc:
        raise WriteRefusedError(getattr(exc, "errno", None) or errno.EIO,
                                f"cannot create {target}: "
                                f"{_write_failure_reason(exc)}") from None
    refused: list[BaseException] = []
    previous_hook = sys.unraisablehook

    def note_refused_writes(unraisable: Any) -> None:
        if "h5py" in repr(unraisable.object) and _is_write_failure(unraisable.exc_value):
            refused.append(unraisable.exc_value)
        previous_hook(unraisable)

    def close_unless_refused() -> None:  # another error ended the block
        if refused:
            _close_without_writing(handle)
            WRITE_FAILURES.append(str(tmp))
        else:
            handle.close()

    def failed(exc: BaseException) -> SessionWriteError:
        WRITE_FAILURES.append(str(tmp))
        return SessionWriteError(refused_write_text(target, exc))

    sys.unraisablehook = note_refused_writes
    try:
        try:
            yield handle
            handle.flush()  # a refused write raises here; inside close() it crashed
            if refused:
                raise refused[0]
        except (OSError, RuntimeError) as exc:
            if not _is_write_failure(exc):
                close_unless_refused()
                raise
            _close_without_writing(handle)
            raise failed(exc) from None
        except BaseException:
            close_unless_refused()
            raise
        try:
            handle.close()
        except (OSError, RuntimeError) as exc:
            raise failed(exc) from None
        if refused:
            raise failed(refused[0])
    finally:
        sys.unraisablehook = previous_hook


def being_written_here(path: Path | str) -> bool:
    """Whether a :class:`SessionWriter` of this process has ``path`` open."""
    return str(Path(path).resolve()) in _WRITING


class SessionWriter:
    """Writes one session file step by step (create it, or open one to resume).

    Not thread-safe: one writer, one thread (the runner's).
    """

    def __init__(self, handle: h5py.File, path: Path, started_monotonic: float,
                 offset_s: float) -> None:
        self._h5 = handle
        self.path = path
        _WRITING.add(str(Path(path).resolve()))
        # a writer dropped without close() (a notebook) leaves the set too; its file is
        # closed by h5py then
        weakref.finalize(self, _WRITING.discard, str(Path(path).resolve()))
        self._t0 = started_monotonic
        self._offset_s = offset_s
        self._largest_step_bytes = 0  # file growth of the largest step written, bytes
        self._frf_index: tuple[np.ndarray, list[str], list[str]] | None = None
        if "frf" in handle:
            g = handle["frf"]
            self._frf_index = (g["frequency_hz"][()],
                               [_text(n) for n in g["outputs/name"][()]],
                               [_text(n) for n in g["inputs/name"][()]])
        self.run_group: h5py.Group | None = None
        self.write_error: str | None = None  # set by the first failed write (_write_guarded)
        self._lines: dict[tuple[int, int, int], list[tuple[complex, float]]] = {}

    # -------------------------------------------------------------- open / create
    @classmethod
    def create(cls, path: Path | str, protocol: Protocol, bench: Mapping[str, Any],
               software_version: str = "", subject_id: str | None = None) -> SessionWriter:
        """A new session file at ``path``; refuses to touch an existing file.

        ``bench``: see :func:`bench_description` (identities, resources, calibration).
        ``subject_id`` overrides the protocol's ``subject.id`` (see :func:`check_subject_id`).
        """
        if subject_id is not None:
            check_subject_id(subject_id)
        path = Path(path)
        if path.exists():
            raise FileExistsError(f"{path} exists; not overwriting it (use --resume to "
                                  "continue that session, or choose another --out)")
        if not path.parent.is_dir():
            raise FileNotFoundError(f"folder {path.parent} does not exist")
        room = file_size_limit_room(path.with_name(".none"))
        if room is not None and room < 16 * 2**20:
            # HDF5 crashed inside the new file's first flush at such a limit (review,
            # session 50): refused before anything is written
            raise SessionFileError(f"cannot create {path}: the file-size limit (ulimit -f) "
                                   f"is {room / 2**20:.2f} MB, under the 16 MB a session "
                                   "needs to start; raise it")
        stale = remove_stale_partials(path)
        # Built under a temporary name and linked into place when complete: a kill during
        # creation must not leave a half-made file at ``path`` (measured: "truncated file").
        tmp = partial_path(path)
        try:
            handle = h5py.File(tmp, "w", libver=("earliest", "v110"))
        except OSError as exc:
            tmp.unlink(missing_ok=True)  # HDF5 may have left it empty (disk full)
            # the system's reason, not HDF5's text naming the temporary file (review)
            raise SessionFileError(f"cannot create {path}: "
                                   f"{_write_failure_reason(exc)}") from None
        try:
            try:
                _fill_new_session(handle, protocol, bench, software_version, subject_id)
            except (OSError, RuntimeError) as exc:
                # a write refused while the file was built (a file-size limit): its close
                # failed the same way and HDF5's clean-up at exit crashed, silently
                # (review, session 50); nothing of it is kept
                _close_without_writing(handle)
                WRITE_FAILURES.append(str(tmp))
                raise SessionWriteError(f"cannot create {path}: "
                                        f"{_write_failure_reason(exc)}") from None
            publish_new_file(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        try:
            handle = h5py.File(path, "r+")
        except OSError as exc:
            raise SessionFileError(f"cannot open the new session {path}: {exc}") from None
        writer = cls(handle, path, time.monotonic(), 0.0)
        for name in stale:
            writer.log(f"removed {name}, left by a session creation killed earlier (process "
                       "no longer running)", "WARNING")
        return writer

    @classmethod
    def resume(cls, path: Path | str, protocol_text: str | None = None) -> SessionWriter:
        """Open an existing session to append steps; checks schema (and protocol text)."""
        path = Path(path)
        with SessionReader(path) as reader:  # schema/version/readability checks
            killed = reader.status[0] in ("running", RUN_RECORD_DAMAGED)
            n_steps = len(reader.step_names())
            stored = reader.protocol_text
            # read before the reserve below: past the old end, a lost chunk reads as zeros
            lines, problems = (salvage_log(reader.handle) if "log" in reader.handle
                               else ([], []))
        reserved = ""
        if killed and (protocol_text is None or stored == protocol_text):
            # before HDF5 opens it for writing: its first allocation comes at the open
            reserved = _reserve_past_recorded_end(path, n_steps)
        try:
            handle = h5py.File(path, "r+")
        except OSError as exc:
            raise SessionFileError(f"{path}: cannot open for appending ({exc})") from None
        stored = _text(handle["protocol"].attrs["toml"])
        if protocol_text is not None and stored != protocol_text:
            handle.close()
            raise SessionFileError(f"{path}: its /protocol differs from the protocol file "
                                   f"given ({first_difference(stored, protocol_text)}); "
                                   "resume with the protocol the session started with")
        created = float(handle.attrs.get("created_unix_s", time.time()))
        if problems:
            # a log damaged by a kill cannot take new lines ("addr overflow": every resume
            # failed; review, session 50): its readable lines go into a new log. The old
            # one is moved aside, not deleted: deleting it frees its lost chunk, whose
            # range runs past the file's recorded end, and the next allocations there
            # corrupted the root group (measured on a killed file); readers read /log only
            try:
                n = sum(1 for name in handle if name.startswith("log_damaged_"))
                handle.move("log", f"log_damaged_{n}")
                create_log(handle, lines)
                handle.flush()
            except Exception as exc:
                handle.close()
                raise SessionFileError(f"{path}: its log is damaged ({problems[0]}) and "
                                       f"could not be replaced ({exc})") from None
        writer = cls(handle, path, time.monotonic(), max(0.0, time.time() - created))
        for problem in problems:
            writer.log(f"the session log was damaged (a kill while it grew?): {problem}; "
                       "its readable lines were copied into a new log", "WARNING")
        if reserved:
            writer.log(reserved, "WARNING")
        return writer

    # -------------------------------------------------------------- writing
    def elapsed_s(self) -> float:
        """Seconds since the session was created (continues across resumed runs)."""
        return self._offset_s + time.monotonic() - self._t0

    @property
    def handle(self) -> h5py.File:
        """The open h5py file (read access for listeners; do not write through it)."""
        return self._h5

    def next_index(self) -> int:
        """Index the next step group will get."""
        names = [n for n in self._h5["steps"] if n.isdigit()]
        return max((int(n) for n in names), default=-1) + 1

    @_write_guarded
    def start_run(self, bench: Mapping[str, Any], software_version: str = "") -> None:
        """Record one run (invocation) under ``/runs/<k>`` with status ``running``."""
        runs = self._h5.require_group("runs")
        k = len(runs)
        g = runs.create_group(f"{k:03d}")
        g.attrs["started_utc"] = _utc_now()
        g.attrs["status"] = "running"
        g.attrs["reason"] = ""
        g.attrs["software_version"] = software_version
        # who writes it: with HDF5 file locking off (NFS), a file being written opens for
        # reading, and only these tell a live run from a killed one (`session info`)
        g.attrs["host"] = socket.gethostname()
        g.attrs["pid"] = os.getpid()
        identity = process_identity(os.getpid())
        if identity is not None:  # Linux: what tells this process from a later one
            g.attrs["boot_id"], g.attrs["pid_start_ticks"] = identity
        _write_bench(g.create_group("bench"), bench)
        # created now, with the run: its first entries, a step later, then add to it and
        # not to the run's own group (a kill in that flush leaves the run's status readable)
        g.create_group("command_logs")
        self.run_group = g
        self._h5.flush()

    @_write_guarded
    def finish_run(self, status: str, reason: str = "",
                   command_logs: Mapping[str, Sequence[tuple[float, str]]] | None = None,
                   unsafe: Sequence[str] = ()) -> None:
        """Record how the run ended and the instruments' command logs; flush. ``unsafe``:
        the safe-state failures of the run (``outputs_confirmed_off`` False, the messages in
        ``safe_state_errors``)."""
        if self.run_group is not None:
            g = self.run_group
            g.attrs["status"] = status
            g.attrs["reason"] = reason
            g.attrs["ended_utc"] = _utc_now()
            g.attrs["outputs_confirmed_off"] = not unsafe
            if unsafe:
                g.attrs["safe_state_errors"] = "\n".join(unsafe)
            self.append_command_logs(command_logs or {})
        self._h5.flush()

    @_write_guarded
    def append_command_logs(self, command_logs: Mapping[str, Sequence[tuple[float, str]]]
                            ) -> None:
        """Append to ``/runs/<k>/command_logs/<role>/{time_s,text}`` the entries of each
        instrument's command log not stored yet (the logs only grow). Called with every
        step, so that a killed run keeps its audit trail up to its last step (before, the
        logs were written only when the run ended: none after kill -9, a closed terminal or
        a full disk). Fixed-length strings (:data:`COMMAND_BYTES`), like ``/log``: no
        global heap that a kill could leave behind. Not flushed here: the step's flush
        does it."""
        if self.run_group is None:
            return
        for role, entries in command_logs.items():
            lg = self.run_group.require_group("command_logs").require_group(role)
            if "time_s" not in lg:
                lg.create_dataset("time_s", shape=(0,), maxshape=(None,), chunks=(64,),
                                  dtype=float)
                lg.create_dataset("text", shape=(0,), maxshape=(None,), chunks=(64,),
                                  dtype=f"S{COMMAND_BYTES}")
            n = lg["time_s"].shape[0]
            # only the tail is copied (a list slice: atomic under the GIL)
            new = entries[n:] if isinstance(entries, (list, tuple)) else list(entries)[n:]
            if not new:
                continue
            for name in ("time_s", "text"):
                lg[name].resize((n + len(new),))
            lg["time_s"][n:] = [float(t) for t, _ in new]
            lg["text"][n:] = [_utf8_cut(text, COMMAND_BYTES) for _, text in new]

    @_write_guarded
    def log(self, message: str, level: str = "INFO", flush: bool = False) -> None:
        """Append one line to the session log (``/log``)."""
        ds = self._h5["log"]
        n = ds.shape[0]
        ds.resize((n + 1,))
        ds[n] = log_entry(f"{self.elapsed_s():10.3f} {level} {' '.join(str(message).split())}")
        if flush:
            self._h5.flush()

    def check_space(self, step_bytes_estimate: int) -> None:
        """Refuse (``OSError`` ENOSPC, before the step is acquired) when the disk cannot take
        the next step with room to spare: three times the larger of ``step_bytes_estimate``
        and the largest step written so far, plus 16 MB for the log and the run's end.

        HDF5 has no way back from a failed write: at "No space left on device" the file
        could not be flushed or closed any more, 140 lines of tracebacks followed and the
        process died with a segmentation fault at exit. Stopped here, the run ends as a
        fault with every complete step on disk, and ``--resume`` continues once space is
        freed."""
        import errno
        import shutil

        need = 3 * max(int(step_bytes_estimate), self._largest_step_bytes) + 16 * 2**20
        free = shutil.disk_usage(self.path.parent).free
        if free < need:
            raise OSError(errno.ENOSPC, f"disk almost full: {free / 2**20:.1f} MB free in "
                          f"{self.path.parent}, the next step needs about "
                          f"{need / 2**20:.1f} MB; free space, then continue with --resume")
        room = file_size_limit_room(self.path)
        if room is not None and room < need:
            # a refused write is no better than a full disk (review, session 50: HDF5
            # crashed inside its flush at a `ulimit -f` limit)
            raise OSError(errno.EFBIG, f"the file-size limit (ulimit -f) leaves "
                          f"{room / 2**20:.1f} MB for {self.path.name}, the next step needs "
                          f"about {need / 2**20:.1f} MB; raise it, then continue with "
                          "--resume")

    @_write_guarded
    def append_step(self, step: StepData) -> int:
        """Write ``step`` as the next ``/steps/<index>`` group, its /frf lines, flush."""
        size_before = _file_size(self.path)
        index = self.next_index()
        g = self._h5["steps"].create_group(f"{index:06d}")
        step.index = index
        g.attrs["setup"] = step.setup
        g.attrs["frequency_hz"] = float(step.frequency_hz)
        _point_attrs(g.attrs, "input", step.input)
        g.attrs["started_at_s"] = float(step.started_at_s)
        g.attrs["drive_vpp"] = float(step.drive_vpp)
        for k, v in step.extra.items():
            g.attrs[k] = _attr_value(v)
        g.create_dataset("force_phasor_n", data=np.complex128(step.force_phasor_n))
        echoes = g.create_group("echoes")
        disp = g.create_group("displacement")
        ph = g.create_group("phasor")
        for c in step.channels:
            codes = np.asarray(c.codes)
            chunks = (min(codes.shape[0], max(1, 65536 // max(1, codes.shape[1]))),
                      codes.shape[1]) if codes.size else None
            ds = echoes.create_dataset(c.name, data=codes, chunks=chunks, **ECHO_COMPRESSION)
            ds.attrs["sample_rate_hz"] = float(c.sample_rate_hz)
            ds.attrs["prf_hz"] = float(c.prf_hz)
            ds.attrs["delay_s"] = float(c.delay_s)
            ds.attrs["volts_per_count"] = float(c.volts_per_count)
            ds.attrs["volts_offset"] = float(c.volts_offset)
            ds.attrs["speed_of_sound_m_s"] = float(c.speed_of_sound_m_s)
            _point_attrs(ds.attrs, "output", c.output)
            echoes.create_dataset(f"{c.name}_trigger_offset_s",
                                  data=np.asarray(c.trigger_offset_s, dtype=np.float64))
            # the quality goes with the displacement; a channel without one (its tracking
            # failed) keeps it on its echoes: why it failed, and the operator's gate, were
            # not in the file (review, session 38)
            quality_attrs = ds.attrs
            if c.displacement_m is not None:
                d = disp.create_dataset(c.name, data=np.asarray(c.displacement_m, dtype=float))
                quality_attrs = d.attrs
            for k, v in c.quality.items():
                quality_attrs[f"quality_{k}"] = _attr_value(v)
            if c.phasor_m is not None:
                p = ph.create_dataset(c.name, data=np.complex128(c.phasor_m))
                p.attrs["std_m"] = float(np.nan if c.phasor_std_m is None else c.phasor_std_m)
        g.attrs["status"] = step.status  # last: a group without it was cut short
        self._h5.flush()  # the step is on disk before /frf mentions it
        if step.status == STATUS_COMPLETE:
            self._write_frf_lines(step)
            self._h5.flush()
        self._largest_step_bytes = max(self._largest_step_bytes,
                                       _file_size(self.path) - size_before)
        return index

    @_write_guarded
    def repair_frf(self) -> int:
        """Rewrite every /frf line from the complete steps in place (after a kill between a
        step's flush and its /frf lines); returns the number of lines written."""
        if self._frf_index is None:
            return 0
        reader = SessionReader.__new__(SessionReader)
        reader.path, reader._h5, reader.damaged, reader.incomplete = self.path, self._h5, [], []
        reader.bone_unstated = set()
        steps = list(reader.steps(with_echoes=False))
        frf = self._h5["frf"]
        freqs, outs, ins = self._frf_index
        rebuilt = frf_from_steps(steps, freqs, _channels_like(frf["outputs"], outs),
                                 _channels_like(frf["inputs"], ins))
        self._lines = {}
        for s in steps:
            if s.status != STATUS_COMPLETE or s.force_phasor_n == 0:
                continue
            i = int(np.argmin(np.abs(freqs - s.frequency_hz)))
            if s.input.name not in ins:
                continue
            j = ins.index(s.input.name)
            for c in s.channels:
                if c.phasor_m is None or c.output.name not in outs or not _usable(c):
                    continue
                std = (np.nan if c.phasor_std_m is None
                       else c.phasor_std_m / abs(s.force_phasor_n))
                self._lines.setdefault((i, outs.index(c.output.name), j), []).append(
                    (c.phasor_m / s.force_phasor_n, std))
        frf["H"][...] = rebuilt.H
        if "H_std" in frf:
            frf["H_std"][...] = rebuilt.H_std
        if "acquired_at_s" in frf and rebuilt.acquired_at_s is not None:
            frf["acquired_at_s"][...] = rebuilt.acquired_at_s
        self._h5.flush()
        return int(np.isfinite(rebuilt.H).sum())

    def _write_frf_lines(self, step: StepData) -> None:
        if self._frf_index is None or step.force_phasor_n == 0:
            return
        freqs, outs, ins = self._frf_index
        i = int(np.argmin(np.abs(freqs - step.frequency_hz)))
        if abs(freqs[i] - step.frequency_hz) > 1e-6 * max(1.0, step.frequency_hz):
            return
        if step.input.name not in ins:
            return
        j = ins.index(step.input.name)
        frf = self._h5["frf"]
        for c in step.channels:
            if c.phasor_m is None or c.output.name not in outs or not _usable(c):
                continue
            o = outs.index(c.output.name)
            std = (np.nan if c.phasor_std_m is None
                   else c.phasor_std_m / abs(step.force_phasor_n))
            values = self._lines.setdefault((i, o, j), [])
            values.append((c.phasor_m / step.force_phasor_n, std))
            h, h_std = combine_lines(values)  # repeats and re-measured lines are merged
            frf["H"][i, o, j] = np.complex128(h)
            if "H_std" in frf:
                frf["H_std"][i, o, j] = h_std
        if "acquired_at_s" in frf:
            frf["acquired_at_s"][i] = step.started_at_s

    @_write_guarded
    def flush(self) -> None:
        """Flush everything written so far to disk."""
        self._h5.flush()

    def close(self) -> None:
        """Flush, close and fsync (idempotent): a session reported complete is on the disk,
        not only in the operating system's cache (a power cut after the run keeps it)."""
        _WRITING.discard(str(Path(self.path).resolve()))
        if self.write_error is not None:
            self._abandon()
            return
        if self._h5.id.valid:
            try:
                self.flush()
            except SessionWriteError:
                self.close()  # as after any failed write
                raise
            self._h5.close()
            try:
                fsync_path(self.path)
            except OSError as exc:  # the data are written; say that the sync failed
                log.error("fsync of %s failed: %s", self.path, exc)

    def _abandon(self) -> None:
        """Give the file up after a failed write without writing to it again
        (:func:`_close_without_writing`: synced, its descriptor pointed at /dev/null, the
        handle left open): a close writes HDF5's metadata and the superblock with the end
        of file it believes in, past what reached the disk, and can crash after a refused
        write."""
        _close_without_writing(self._h5)

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


MAX_COMPACT_LINKS = 1000
"""Links a pre-sized group keeps in its object header (:func:`_presized_group`)."""


def _file_size(path: Path) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


def _hdf5_library() -> Any:
    """The HDF5 C library h5py uses (already loaded: same state, same identifiers), for
    the two group-creation properties h5py does not expose; None where it cannot be found
    (the groups are then created plainly)."""
    import ctypes

    try:
        with open("/proc/self/maps") as maps:  # Linux; elsewhere: None
            paths = {line.split()[-1] for line in maps if "libhdf5" in line}
    except OSError:
        return None
    # h5py's own copy first (another package may have loaded another HDF5), and only one
    # whose version is h5py's: its property-list identifiers mean the same there
    for path in sorted(paths, key=lambda p: "h5py" not in p):
        name = Path(path).name
        if name.startswith("libhdf5") and not name.startswith("libhdf5_hl"):
            try:
                lib = ctypes.CDLL(path)
                major, minor, release = (ctypes.c_uint() for _ in range(3))
                if lib.H5get_libversion(ctypes.byref(major), ctypes.byref(minor),
                                        ctypes.byref(release)) < 0 or (
                        major.value, minor.value, release.value
                        ) != tuple(h5py.version.hdf5_version_tuple[:3]):
                    continue
                for fn in (lib.H5Pset_link_phase_change, lib.H5Pset_est_link_info):
                    fn.argtypes = [ctypes.c_int64, ctypes.c_uint, ctypes.c_uint]
                    fn.restype = ctypes.c_int
                return lib
            except (OSError, AttributeError):
                continue
    return None


def _presized_group(parent: h5py.Group, name: str, n_links: int) -> h5py.Group:
    """Create ``parent/name`` with its links stored in its own object header, sized for
    ``n_links`` links (at most :data:`MAX_COMPACT_LINKS`; beyond, HDF5 moves them to dense
    storage).

    Why: a plain group keeps its links in a B-tree of symbol-table nodes with a local
    heap, which HDF5 moves or splits into newly allocated space as links are added. A
    flush writes metadata in address order and the superblock (with the end-of-file
    address) last, so a kill -9 inside the flush that first added a step left the
    moved ``/steps`` structures beyond the recorded end of file: ``/steps`` unreadable
    ("addr overflow"; strace fault injection killing an 8-step run at each write call:
    7 of the first 253 kill points, all in the first step's flush). Pre-sized, adding a
    link rewrites the header in place; a kill then loses at most the step being written."""
    lib = _hdf5_library()
    # at most 1000 links in the header (40 kB): past ~1600 (a header over 64 kB) HDF5's
    # move to dense storage, when a link more arrives, was measured to stall for minutes
    # holding the GIL (4 ms at 1600 links, > 150 s at 1800); up to 1500 it takes < 10 ms.
    # A plan of more steps goes dense at step 1001, one flush like the plain group's.
    n = int(min(max(n_links, 8), MAX_COMPACT_LINKS))
    if lib is None:
        return parent.create_group(name)
    from h5py._objects import phil  # h5py's lock around every HDF5 call

    gcpl = h5py.h5p.create(h5py.h5p.GROUP_CREATE)
    # tracking the creation order is what makes HDF5 store the links in the header (the
    # "new-style" group) in a file whose format bound is "earliest"
    gcpl.set_link_creation_order(h5py.h5p.CRT_ORDER_TRACKED)
    with phil:  # the bundled HDF5 is not thread-safe: no other thread in it meanwhile
        failed = (lib.H5Pset_link_phase_change(gcpl.id, n, max(n - 1, 1)) < 0
                  or lib.H5Pset_est_link_info(gcpl.id, n, 8) < 0)
    if failed:
        return parent.create_group(name)
    return h5py.Group(h5py.h5g.create(parent.id, name.encode(), gcpl=gcpl))


def _rename_noreplace(tmp: Path, path: Path) -> bool:
    """Rename ``tmp`` to ``path`` atomically unless ``path`` exists (Linux ``renameat2`` with
    ``RENAME_NOREPLACE``). False when the call is not available here (other systems, old
    glibc, a file system that does not support the flag); raises FileExistsError."""
    import ctypes
    import errno
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_noreplace = -100, 1
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                          ctypes.c_uint]
    if renameat2(at_fdcwd, os.fsencode(tmp), at_fdcwd, os.fsencode(path),
                 rename_noreplace) == 0:
        return True
    code = ctypes.get_errno()
    if code == errno.EEXIST:
        raise FileExistsError(f"{path} exists; not overwriting it")
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(code, f"cannot rename {tmp} to {path}: {os.strerror(code)}")


def publish_new_file(tmp: Path, path: Path) -> None:
    """Give the finished file ``tmp`` the name ``path``, never replacing an existing file
    (raises FileExistsError then; ``tmp`` is left for the caller to remove)."""
    fsync_path(tmp)
    try:
        os.link(tmp, path)  # atomic, and fails if path exists
    except FileExistsError:
        raise FileExistsError(f"{path} exists; not overwriting it") from None
    except OSError:  # a file system without hard links
        if not _rename_noreplace(tmp, path):
            # last resort: on Windows os.rename itself refuses an existing target; elsewhere
            # (no hard links and no renameat2, e.g. exFAT on macOS) a file that appears
            # between the check and the rename would be replaced
            if path.exists():
                raise FileExistsError(f"{path} exists; not overwriting it") from None
            os.rename(tmp, path)
    fsync_path(path)  # the new name's folder entry, which the sync of tmp did not cover


def _channels_like(group: h5py.Group, names: list[str]) -> Channels:
    return Channels(names, [_text(b) for b in group["bone"][()]], group["position_m"][()],
                    group["direction"][()])


def _write_bench(g: h5py.Group, bench: Mapping[str, Any]) -> None:
    for key, value in bench.items():
        if isinstance(value, Mapping):
            sub = g.create_group(str(key))
            for k, v in value.items():
                sub.attrs[str(k)] = _attr_value(v)
        else:
            g.attrs[str(key)] = _attr_value(value)


def bench_description(bench: Any) -> dict[str, Any]:
    """/bench content of an open :class:`pelvislab.drivers.bench.Bench`."""
    cfg = bench.config
    out: dict[str, Any] = {
        "simulated": bool(bench.simulated),
        "name": str(cfg.name),
        "source": str(cfg.source) if cfg.source is not None else "",
        "drive_newton_per_volt": np.complex128(cfg.drive_newton_per_volt),
        "max_drive_vpp": float(cfg.max_drive_vpp),
        # NaN: the bench file states none, the protocol's applies (what each channel
        # used is on its echoes datasets)
        "speed_of_sound_m_s": (math.nan if cfg.speed_of_sound_m_s is None
                               else float(cfg.speed_of_sound_m_s)),
        "reference_clock_hz": float(cfg.reference_clock_hz),
    }
    table_hz = tuple(getattr(cfg, "drive_calibration_frequency_hz", ()))
    if table_hz:
        # the per-frequency calibration in full: the FRFs' denominators, re-derivable
        out["drive_calibration_frequency_hz"] = np.asarray(table_hz, dtype=float)
        out["drive_calibration_newton_per_volt"] = np.asarray(
            cfg.drive_calibration_newton_per_volt, dtype=np.complex128)
        out["drive_calibration_file"] = str(cfg.drive_calibration_source or "")
    u_rel = tuple(getattr(cfg, "drive_calibration_u_rel", ()))
    if u_rel:
        # one value (for drive_newton_per_volt) or one per row of the table
        out["drive_calibration_u_rel"] = np.asarray(u_rel, dtype=float)
    for ch, c in dict(cfg.channel_speed_of_sound_m_s).items():
        out[f"speed_of_sound_m_s_ch{ch}"] = float(c)
    roles = [("trigger", bench.trigger), ("drive", bench.drive), ("digitizer", bench.digitizer)]
    roles += [(f"pulser{i + 1}", p) for i, p in enumerate(bench.pulsers)]
    for role, inst in roles:
        out[role] = {"identity": str(getattr(inst, "identity", "")),
                     "resource": str(getattr(inst, "resource", ""))}
    return out


# --------------------------------------------------------------------------- reader
class SessionReader:
    """Read access to a session file with clear one-line errors for anything else.

    ``steps()`` yields complete steps; ``damaged`` lists groups that could not be read and
    ``incomplete`` those whose status is not ``complete`` (cut short or failed).
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"no such session file: {self.path}")
        try:
            self._h5 = h5py.File(self.path, "r")
        except OSError as exc:
            reason = " ".join(str(exc).split())[:160]
            if "unable to lock file" in reason.lower():  # HDF5's lock: a writer has it open
                raise SessionFileError(f"{self.path} is in use by another process (a run in "
                                       f"progress?); try again when it has finished: "
                                       f"{reason}") from None
            end = recorded_end_of_file(self.path)
            if end is not None and self.path.stat().st_size < end:
                raise SessionFileError(
                    f"{self.path} ends {end - self.path.stat().st_size} bytes before the end "
                    "its superblock records: a copy cut short (copy it again), or a write "
                    "that failed part way (a full disk, a file-size limit), which `pelvislab "
                    f"run PROTOCOL --out {self.path} --resume` extends and goes on from (the "
                    "steps written before are kept)") from None
            raise SessionFileError(f"{self.path} is not a readable HDF5 file (truncated or "
                                   f"damaged?): {reason}") from None
        try:
            schema = _text(self._h5.attrs.get("schema", ""))
            if not schema:  # another program's HDF5 file
                raise SessionFileError(f"{self.path} is an HDF5 file but not a pelvislab "
                                       f"session (no 'schema' attribute {SESSION_SCHEMA!r})",
                                       schema="")
            if schema != SESSION_SCHEMA:
                hint = " (an FRF-only file?)" if schema == "pelvislab-frf" else ""
                raise SessionFileError(f"{self.path} has schema {schema!r}, expected "
                                       f"{SESSION_SCHEMA!r}{hint}", schema=schema)
            version = self._h5.attrs.get("schema_version", None)
            try:
                version = int(version)  # type: ignore[arg-type]
            except (TypeError, ValueError):
                version = None
            if version != SESSION_SCHEMA_VERSION:
                raise SessionFileError(f"{self.path} has schema_version {version!r}; this "
                                       f"pelvislab reads {SESSION_SCHEMA_VERSION}")
            for required in ("protocol", "steps"):
                if required not in self._h5:
                    raise SessionFileError(f"{self.path} lacks the /{required} group")
        except BaseException:
            self._h5.close()
            raise
        self.damaged: list[str] = []
        self.incomplete: list[str] = []
        self.bone_unstated: set[tuple[str, str]] = set()
        """(``"output"`` or ``"input"``, name) of the points read so far that nothing
        gives a bone: no ``<prefix>_bone`` attribute and not in the landmark catalogue.
        They read as bone "" (on no modelled bone) for want of another word, which is not
        the file saying so (our writer always writes ``<prefix>_bone``, "" included)."""

    @property
    def handle(self) -> h5py.File:
        """The open h5py file (read-only)."""
        return self._h5

    @property
    def attrs(self) -> dict[str, Any]:
        """Root attributes."""
        return {k: self._h5.attrs[k] for k in self._h5.attrs}

    @property
    def protocol_text(self) -> str:
        """The protocol TOML the session was run with."""
        try:
            return _text(self._h5["protocol"].attrs.get("toml", ""))
        except Exception as exc:
            raise SessionFileError(f"{self.path}: /protocol is unreadable: "
                                   f"{' '.join(str(exc).split())[:160]}") from None

    @property
    def status(self) -> tuple[str, str]:
        """(status, reason) of the last run (``/runs``): completed, aborted, interrupted,
        failed, or running (the process ended without closing the session: killed);
        ``damaged`` when its record cannot be read (see :func:`run_records`)."""
        records = run_records(self._h5)
        if not records:
            return ("unknown", "")
        _name, attrs, problem = records[-1]
        if attrs is None:
            return (RUN_RECORD_DAMAGED, problem)
        return (_text(attrs.get("status", "unknown")), _text(attrs.get("reason", "")))

    @property
    def outputs_confirmed_off(self) -> bool | None:
        """False when any run's end could not confirm every output off (``/runs``
        attribute; a resumed session keeps its earlier runs' record), True when every run
        that recorded it confirmed them, None when none did (killed runs, or a file from
        before session 31; a damaged record counts as none)."""
        values = [attrs.get("outputs_confirmed_off")
                  for _, attrs, _ in run_records(self._h5) if attrs is not None]
        known = [bool(v) for v in values if v is not None]
        return None if not known else all(known)

    def log_lines(self) -> list[str]:
        """The session log."""
        if "log" not in self._h5:
            return []
        lines, problems = salvage_log(self._h5)
        return lines + [f"(session log: {p})" for p in problems]

    def bench(self) -> dict[str, Any]:
        """/bench attributes, roles as nested dicts."""
        out: dict[str, Any] = {}
        g = self._h5.get("bench")
        if g is None:
            return out
        out.update({k: g.attrs[k] for k in g.attrs})
        for k, sub in g.items():
            out[k] = {a: _text(sub.attrs[a]) for a in sub.attrs}
        return out

    def step_names(self) -> list[str]:
        """Names of every step group, in acquisition order."""
        try:
            return sorted(n for n in self._h5["steps"] if n.isdigit())
        except Exception as exc:
            raise SessionFileError(f"{self.path}: /steps is unreadable (damaged file?): "
                                   f"{' '.join(str(exc).split())[:160]}") from None

    def steps(self, include_incomplete: bool = False, with_echoes: bool = True,
              ) -> Iterator[StepData]:
        """Readable steps in acquisition order (complete ones unless asked otherwise)."""
        self.damaged = []
        self.incomplete = []
        for name in self.step_names():
            try:
                step = self.read_step(name, with_echoes)
            except Exception as exc:  # a group cut short by a kill: report, go on
                self.damaged.append(f"{name}: {' '.join(str(exc).split())[:120]}")
                continue
            if step.status != STATUS_COMPLETE:
                self.incomplete.append(f"{name}: status {step.status!r}")
                if not include_incomplete:
                    continue
            yield step

    def read_step(self, name: str, with_echoes: bool = True) -> StepData:
        """One step group (raises for a damaged one)."""
        g = self._h5["steps"][name]
        a = g.attrs
        status = _text(a.get("status", "incomplete"))
        if status.strip().lower() in STATUS_COMPLETE_ALIASES:
            status = STATUS_COMPLETE
        echoes = g["echoes"] if "echoes" in g else {}
        channels: list[ChannelData] = []
        for ch in sorted(k for k in echoes if not k.endswith("_trigger_offset_s")):
            ds = echoes[ch]
            ea = ds.attrs
            disp = g["displacement"][ch][()] if ch in g.get("displacement", {}) else None
            # on the displacement; on the echoes for a channel whose tracking failed
            dq = g["displacement"][ch].attrs if ch in g.get("displacement", {}) else ea
            quality = {k[len("quality_"):]: dq[k] for k in dq if k.startswith("quality_")}
            ph = g["phasor"][ch] if ch in g.get("phasor", {}) else None
            channels.append(ChannelData(
                name=ch,
                codes=ds[()] if with_echoes else np.empty((0, 0), dtype=ds.dtype),
                trigger_offset_s=echoes[f"{ch}_trigger_offset_s"][()] if with_echoes
                else np.empty(0),
                sample_rate_hz=float(ea["sample_rate_hz"]), prf_hz=float(ea["prf_hz"]),
                delay_s=float(ea["delay_s"]), volts_per_count=float(ea["volts_per_count"]),
                volts_offset=float(ea["volts_offset"]),
                speed_of_sound_m_s=float(ea["speed_of_sound_m_s"]),
                output=self._point(ea, "output"),
                displacement_m=disp,
                phasor_m=complex(ph[()]) if ph is not None else None,
                phasor_std_m=float(ph.attrs.get("std_m", np.nan)) if ph is not None else None,
                quality=quality,
            ))
        known = {"setup", "frequency_hz", "started_at_s", "status", "drive_vpp", "input",
                 "input_bone", "input_position_m", "input_direction"}
        return StepData(
            setup=_text(a["setup"]), frequency_hz=float(a["frequency_hz"]),
            input=self._point(a, "input"), started_at_s=float(a["started_at_s"]),
            channels=channels,
            force_phasor_n=complex(g["force_phasor_n"][()]) if "force_phasor_n" in g else 0j,
            drive_vpp=float(a.get("drive_vpp", np.nan)), status=status, index=int(name),
            extra={k: a[k] for k in a if k not in known},
        )

    def _point(self, attrs: h5py.AttributeManager, prefix: str) -> Point:
        """:func:`_read_point`, noting in :attr:`bone_unstated` a point whose bone nothing
        gives."""
        point = _read_point(attrs, prefix)
        if attrs.get(f"{prefix}_bone") is None and point.name not in _catalogue():
            self.bone_unstated.add((prefix, point.name))
        return point

    def frf(self) -> FrfSet:
        """The stored /frf set."""
        if "frf" not in self._h5:
            raise SessionFileError(f"{self.path} holds no /frf group")
        try:
            return read_frf_group(self._h5["frf"])
        except ValueError:
            raise
        except Exception as exc:
            raise SessionFileError(f"{self.path}: /frf is unreadable (damaged file?): "
                                   f"{' '.join(str(exc).split())[:160]}") from None

    def frf_layout(self) -> tuple[list[float], Channels, Channels] | None:
        """(frequencies, outputs, inputs) of the stored /frf, or None."""
        try:
            frf = self.frf()
        except Exception:
            return None
        return list(frf.frequency_hz), frf.outputs, frf.inputs

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._h5.id.valid:
            self._h5.close()

    def __enter__(self) -> SessionReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


RUN_RECORD_DAMAGED = "damaged"
"""The status :func:`run_records` readers give a run whose ``/runs/<k>`` cannot be read."""


def run_records(h5: h5py.File | h5py.Group) -> list[tuple[str, dict[str, Any] | None, str]]:
    """Each run's record of ``/runs`` in order: ``(name, attributes, "")``, or
    ``(name, None, why)`` when its group cannot be read.

    A kill -9 (or a power cut) while HDF5 flushed a run's record, as its run started or
    ended, can leave that one group's object header half written: the steps and /frf were
    whole, yet every tool refused the file ("unable to determine object type"; review,
    session 50). A damaged record says so and the rest of the file stays readable."""
    runs = h5.get("runs") if isinstance(h5, h5py.Group) else None
    if not isinstance(runs, h5py.Group):
        return []
    records: list[tuple[str, dict[str, Any] | None, str]] = []
    for name in sorted(runs):
        try:
            records.append((name, dict(runs[name].attrs), ""))
        except Exception as exc:  # HDF5 says KeyError, OSError or RuntimeError here
            reason = " ".join(str(exc).strip("'\"").split())[:160]
            records.append((name, None, f"the record of run {name} is unreadable ({reason}): "
                            "the process was probably killed while it wrote it, as the run "
                            "started or ended"))
    return records


def _read_point(attrs: h5py.AttributeManager, prefix: str) -> Point:
    """The point ``prefix`` (``output`` of an echoes dataset, ``input`` of a step) from its
    attributes. Design 4.2 names only the point (``output``, ``input``); its bone, position
    and direction (``<prefix>_bone``, ``_position_m``, ``_direction``) are this writer's.
    Where they are missing, a point of the landmark catalogue takes its geometry from there
    (an input's direction into the surface, the protocols' default), so that a session
    written from the design alone re-processes (its /steps are self-describing); else NaN."""
    name = _text(attrs.get(prefix, ""))
    bone = attrs.get(f"{prefix}_bone")
    pos = attrs.get(f"{prefix}_position_m")
    direction = attrs.get(f"{prefix}_direction")
    missing = any(v is None for v in (bone, pos, direction))
    known = _catalogue().get(name) if missing else None
    if known is not None:
        bone = known.bone if bone is None else bone
        pos = known.position_m if pos is None else pos
        if direction is None:
            sign = -1.0 if prefix == "input" else 1.0
            direction = tuple(sign * v for v in known.direction)
    return Point(
        name, _text(bone if bone is not None else ""),
        tuple(float(v) for v in (pos if pos is not None else (np.nan,) * 3)),  # type: ignore
        tuple(float(v) for v in (direction if direction is not None else (np.nan,) * 3)),
    )


_CATALOGUE: dict[str, dict[str, Point]] = {}


def _catalogue() -> dict[str, Point]:
    """The shipped landmark catalogue, read once (empty when it cannot be read: said once,
    not at every point of every step)."""
    if "shipped" not in _CATALOGUE:
        from pelvislab.acquisition.protocol import load_landmarks

        try:
            _CATALOGUE["shipped"] = load_landmarks()
        except Exception:  # a fallback only: the file's own attributes rule
            _CATALOGUE["shipped"] = {}
            log.warning("landmark catalogue unreadable: foreign sessions' points keep NaN")
    return _CATALOGUE["shipped"]


def fsync_path(path: Path | str) -> None:
    """fsync a closed file (after creating a session and after closing it), and on POSIX
    its folder, so that the name reaches the disk too (a new file's directory entry).
    Windows needs write access to flush a file; its folders cannot be opened."""
    fd = os.open(path, os.O_RDWR if os.name == "nt" else os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    if os.name != "nt":
        try:
            folder = os.open(Path(path).parent, os.O_RDONLY)
        except OSError:
            return
        try:
            os.fsync(folder)
        except OSError:  # some file systems refuse fsync on a folder: the file is synced
            pass
        finally:
            os.close(folder)
