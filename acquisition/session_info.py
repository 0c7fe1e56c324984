"""What a session or FRF-only file holds, at a glance (``pelvislab session info``).

An analyst handed an HDF5 file wants to know, before any analysis, whose it is, how each
run ended (and whether the outputs were confirmed off), how much of the protocol's plan it
holds, how good the tracking was per channel, and what ``/frf`` offers (lines, points,
``H_std``). :func:`session_info` reads that without the raw echoes; the CLI prints it as
text or JSON (docs/session-format.md, "At a glance").
"""

from __future__ import annotations

import os
import socket
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from pelvislab.acquisition.frfset import FRF_SCHEMA, FrfSet, existing_file, read_frf
from pelvislab.acquisition.session import (
    RUN_RECORD_DAMAGED,
    SESSION_SCHEMA,
    STATUS_COMPLETE,
    STATUS_COMPLETE_ALIASES,
    SessionReader,
    being_written_here,
    process_identity,
    run_records,
)

#: Session log lines kept in the summary (the latest warnings and errors).
LOG_LINES_KEPT = 5


def _text(value: Any) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace").rstrip("\x00").strip()
    if isinstance(value, np.ndarray) and value.size == 1:
        return _text(value.reshape(-1)[0])
    return str(value)


def _number(value: Any) -> float | None:
    try:
        x = float(np.asarray(value).reshape(-1)[0])
    except (TypeError, ValueError, IndexError):
        return None
    return x if np.isfinite(x) else None


def frf_info(frf: FrfSet, planned_pairs: set[tuple[str, str]] | None = None) -> dict[str, Any]:
    """The FRF set at a glance: lines (count, range, spacing), points with their bones,
    which (output, input) pairs hold data and on how many lines, whether ``H_std`` is
    given. ``planned_pairs``: the (output, input) names the protocol measures, if known."""
    f = frf.frequency_hz
    measured = np.isfinite(frf.H) & (np.abs(np.nan_to_num(frf.H)) > 0)
    lines_held = measured.sum(axis=0)  # (n_out, n_in)
    spacing = np.diff(f)
    pairs = []
    for o, out_name in enumerate(frf.outputs.name):
        for i, in_name in enumerate(frf.inputs.name):
            if planned_pairs is not None and (out_name, in_name) not in planned_pairs \
                    and not lines_held[o, i]:
                continue  # a cell of the layout the protocol never measures
            pairs.append({"output": out_name, "input": in_name,
                          "lines_measured": int(lines_held[o, i])})
    std_given = frf.H_std is not None and bool(
        np.any(np.isfinite(frf.H_std[measured]) & (frf.H_std[measured] > 0)))
    return {
        "lines": int(f.size),
        "frequency_hz": [float(f[0]), float(f[-1])] if f.size else None,
        "spacing_hz": [float(spacing.min()), float(spacing.max())] if spacing.size else None,
        "lines_with_data": int(measured.any(axis=(1, 2)).sum()),
        "outputs": [{"name": n, "bone": b} for n, b in zip(frf.outputs.name,
                                                            frf.outputs.bone, strict=True)],
        "inputs": [{"name": n, "bone": b} for n, b in zip(frf.inputs.name,
                                                           frf.inputs.bone, strict=True)],
        "pairs": pairs,
        "pairs_measured": int(sum(1 for p in pairs if p["lines_measured"])),
        "pairs_planned": len(planned_pairs) if planned_pairs is not None else None,
        "h_std": std_given,
    }


def session_info(path: str | Path) -> dict[str, Any]:
    """A summary of the session (schema ``pelvislab-session``) or FRF-only file
    (``pelvislab-frf``) at ``path``: a JSON-ready dict (keys in docs/session-format.md).

    Raises the readers' one-line errors (FileNotFoundError, SessionFileError,
    FrfFileError) for anything else. Damaged or unfinished steps are counted, not
    raised."""
    path = existing_file(path)
    try:
        with h5py.File(path, "r") as handle:
            schema = _text(handle.attrs.get("schema", ""))
    except OSError:
        schema = ""  # the session reader says why (in use, damaged) in one line
    if schema != SESSION_SCHEMA and (schema == FRF_SCHEMA or _is_frf_only(path)):
        frf = read_frf(path)
        return {"file": str(path), "kind": "frf-only", "schema": FRF_SCHEMA,
                "frf": frf_info(frf), "notes": []}
    with SessionReader(path) as reader:
        return _session(reader, path)


def _is_frf_only(path: Path) -> bool:
    try:
        with h5py.File(path, "r") as handle:
            return "frf" in handle and "steps" not in handle
    except OSError:
        return False


def _session(reader: SessionReader, path: Path) -> dict[str, Any]:
    from pelvislab.acquisition.protocol import parse_protocol

    attrs = reader.attrs
    notes: list[str] = []
    protocol = None
    try:
        protocol = parse_protocol(reader.protocol_text, source=f"{path}:/protocol")
    except Exception as exc:  # a record, not an input: summarise the rest
        notes.append(f"the stored protocol does not parse ({' '.join(str(exc).split())[:160]}):"
                     " the plan is unknown")
    h5 = reader.handle
    runs = []
    for name, a, problem in run_records(h5):
        if a is None:  # a kill while its record was flushed: the rest is readable
            notes.append(problem)
            runs.append({"index": int(name) if name.isdigit() else name, "started_utc": "",
                         "ended_utc": None, "status": RUN_RECORD_DAMAGED, "reason": problem,
                         "outputs_confirmed_off": None, "simulated": None,
                         "software_version": "", **_writer_record({})})
            continue
        try:
            bench = h5["runs"][name].get("bench")
        except Exception:  # its bench group damaged alone
            bench = None
        confirmed = a.get("outputs_confirmed_off")
        runs.append({
            "index": int(name) if name.isdigit() else name,
            "started_utc": _text(a.get("started_utc", "")),
            "ended_utc": _text(a.get("ended_utc", "")) or None,
            "status": _text(a.get("status", "unknown")),
            "reason": _text(a.get("reason", "")),
            "outputs_confirmed_off": None if confirmed is None else bool(confirmed),
            "simulated": None if bench is None or "simulated" not in bench.attrs
            else bool(bench.attrs["simulated"]),
            "software_version": _text(a.get("software_version", "")),
            **_writer_record(a),
        })
    status, reason = reader.status
    steps, damaged = _scan_steps(h5)
    complete = [s for s in steps if s.status == STATUS_COMPLETE]
    planned = protocol.steps() if protocol is not None else None
    done_keys = {s.key for s in complete}
    by_setup: list[dict[str, Any]] = []
    if protocol is not None:
        for si, setup in enumerate(protocol.setups):
            plan = [p for p in planned if p.setup_index == si]
            mine = [s for s in complete if s.setup == setup.name]
            by_setup.append({
                "setup": setup.name, "excitation": setup.excitation,
                "transducers": {f"ch{c}": p for c, p in sorted(setup.transducers.items())},
                "planned": len(plan),
                "acquired": sum(1 for p in plan if p.key in done_keys),
                "quality_not_ok": sum(1 for s in mine if not _quality_ok(s)),
            })
    channels: dict[str, dict[str, Any]] = {}
    for name in sorted({c.name for s in complete for c in s.channels}):
        records = [c for s in complete for c in s.channels if c.name == name]
        lost = np.array([_number(c.quality.get("lost_fraction")) for c in records
                         if _number(c.quality.get("lost_fraction")) is not None])
        snr = np.array([_number(c.quality.get("snr_db_median")) for c in records
                        if _number(c.quality.get("snr_db_median")) is not None])
        # a record without tracking quality (a file written from design 4.2 alone) has
        # none to count: its defaults ("ok", gate "auto") read as data (review, session 43)
        gates = Counter(_text(c.quality.get("gate_source", "auto")) if c.quality
                        else "not recorded" for c in records)
        channels[name] = {
            "records": len(records),
            "quality_not_recorded": sum(1 for c in records if not c.quality),
            "quality_not_ok": sum(1 for c in records
                                  if "ok" in c.quality and not bool(c.quality["ok"])),
            "lost_fraction_median": float(np.median(lost)) if lost.size else None,
            "lost_fraction_max": float(lost.max()) if lost.size else None,
            "snr_db_median": float(np.median(snr)) if snr.size else None,
            "gate_sources": dict(sorted(gates.items())),
            "tracker_notes": sum(1 for c in records
                                 if _text(c.quality.get("tracking_warnings", ""))),
        }
    planned_pairs = None
    if protocol is not None:
        planned_pairs = {(point, setup.excitation) for setup in protocol.setups
                         for point in setup.transducers.values()}
    frf = None
    try:
        frf = frf_info(reader.frf(), planned_pairs)
    except Exception as exc:
        notes.append(f"/frf unreadable: {' '.join(str(exc).split())[:160]}")
    log = reader.log_lines()
    flagged = [line.strip() for line in log
               if " WARNING " in f" {line} " or " ERROR " in f" {line} "]
    bench = reader.bench()
    if damaged:
        notes.append(f"{damaged} step group(s) unreadable (a kill while writing?)")
    source = attrs.get("reprocessed_from")
    return {
        "file": str(path),
        "kind": "reprocessed" if source is not None else "session",
        "schema": SESSION_SCHEMA,
        "schema_version": int(attrs.get("schema_version", 0)),
        "created_utc": _text(attrs.get("created_utc", "")),
        "software_version": _text(attrs.get("software_version", "")),
        "protocol_name": _text(attrs.get("protocol_name", ""))
        or (protocol.name if protocol is not None else ""),
        "subject_id": _text(attrs.get("subject_id", "")) or None,
        "subject_position": _text(attrs.get("subject_position", "")) or None,
        "reprocessed_from": _text(source) if source is not None else None,
        "protocol_source": _text(h5["protocol"].attrs.get("source", "")) or None,
        "protocol_source_state": _source_state(
            _text(h5["protocol"].attrs.get("source", "")), reader.protocol_text),
        "status": status, "reason": reason,
        "writer_alive": (_writer_alive(runs[-1], path)
                         if status == "running" and runs and source is None else None),
        "outputs_confirmed_off": reader.outputs_confirmed_off,
        "runs": runs,
        "bench": {
            "simulated": None if "simulated" not in bench else bool(bench["simulated"]),
            "name": _text(bench.get("name", "")),
            "drive_newton_per_volt": _complex_text(bench.get("drive_newton_per_volt")),
            "drive_calibration_rows": int(np.size(bench["drive_calibration_frequency_hz"]))
            if "drive_calibration_frequency_hz" in bench else None,
            "speed_of_sound_m_s": _number(bench.get("speed_of_sound_m_s")),
        },
        "steps": {
            "planned": len(planned) if planned is not None else None,
            "acquired": len(done_keys),
            "groups": len(steps) + damaged,
            "incomplete": len(steps) - len(complete),
            "damaged": damaged,
            "quality_not_ok": sum(1 for s in complete if not _quality_ok(s)),
            "by_setup": by_setup,
        },
        "channels": channels,
        "frf": frf,
        "log": {"lines": len(log), "warnings": sum(1 for x in flagged if " WARNING " in
                                                    f" {x} "),
                "errors": sum(1 for x in flagged if " ERROR " in f" {x} "),
                "latest_flagged": flagged[-LOG_LINES_KEPT:]},
        "notes": notes,
    }


def last_run_writer_alive(h5: h5py.File, path: Path | str) -> bool | None:
    """:func:`_writer_alive` of the last run in ``/runs`` of the open session file at
    ``path`` (None without runs, or for a reprocessed file: its runs are its source's)."""
    records = run_records(h5)
    if not records or "reprocessed_from" in h5.attrs or records[-1][1] is None:
        return None
    return _writer_alive(_writer_record(records[-1][1]), path)


def _writer_record(attrs: Any) -> dict[str, Any]:
    """The writing process a run recorded (``host``, ``pid``, ``boot_id``,
    ``pid_start_ticks``; None where absent or unreadable: a file from before session 44,
    another tool's, a hand-edited one; readers ignore what they do not know)."""
    def number(key: str) -> int | None:
        try:
            value = int(attrs[key])
        except (KeyError, TypeError, ValueError, OverflowError):
            return None
        return value if value > 0 else None

    return {"host": _text(attrs.get("host", "")) or None, "pid": number("pid"),
            "boot_id": _text(attrs.get("boot_id", "")) or None,
            "pid_start_ticks": number("pid_start_ticks")}


def _writer_alive(run: Mapping[str, Any], path: Path | str) -> bool | None:
    """Whether the process that wrote ``run`` is still running: True only when this machine
    (same host and boot) has a process of that pid started at the recorded time (and, for
    this very process, a writer of its own has ``path`` open); False when it has ended (the
    run was killed); None when that cannot be told (another host, no /proc, a file from
    before the identity was recorded). With HDF5 file locking on, a file being written does
    not open at all; with it off (NFS), this tells a live run from a killed one. A pid
    alone does not: after a reboot, or in time, another process holds it (review)."""
    if (run.get("pid") is None or run.get("host") != socket.gethostname()
            or run.get("boot_id") is None or run.get("pid_start_ticks") is None):
        return None
    now = process_identity(run["pid"])
    if now is None:  # gone, or no /proc here any more
        here = process_identity(os.getpid())
        return None if here is None else False
    if now != (run["boot_id"], run["pid_start_ticks"]):
        return False  # rebooted since, or the pid is another process's now
    if run["pid"] == os.getpid():
        return being_written_here(path)
    return True


def _source_state(source: str, text: str) -> str | None:
    """Whether the protocol file the session was run with (``/protocol`` ``source``, as
    given to ``run``: relative to the folder it was run in) holds the stored protocol text
    now, read from the current folder: ``matches``, ``differs``, ``missing``; None when no
    source is recorded. ``run --resume`` needs a file holding that very text."""
    if not source:
        return None
    try:
        return "matches" if Path(source).read_text(encoding="utf-8") == text else "differs"
    except UnicodeDecodeError:
        return "differs"
    except OSError:
        return "missing"


@dataclass
class _StepAtAGlance:
    """The attributes of one step group the summary uses (no dataset is read)."""

    setup: str
    key: tuple[str, float, int]
    status: str
    quality_ok: Any
    channels: list[_ChannelAtAGlance] = field(default_factory=list)


@dataclass
class _ChannelAtAGlance:
    name: str
    quality: dict[str, Any]


#: The tracking-quality attributes the summary reads, without their ``quality_`` prefix.
QUALITY_KEYS = ("ok", "lost_fraction", "snr_db_median", "gate_source", "tracking_warnings")


def _scan_steps(h5: h5py.File) -> tuple[list[_StepAtAGlance], int]:
    """Every step group's attributes the summary needs, and the number of groups that
    could not be read (a kill while writing). Attributes only: ``SessionReader.steps``
    also reads each channel's displacement and phasor (~7 ms a step: 2.3 s of the demo's
    308-step session), which the summary does not use."""
    steps: list[_StepAtAGlance] = []
    damaged = 0
    for name in sorted(n for n in h5["steps"] if n.isdigit()):
        try:
            g = h5["steps"][name]
            a = g.attrs
            status = _text(a.get("status", "incomplete")).strip().lower()
            setup = _text(a["setup"])
            step = _StepAtAGlance(
                setup=setup,
                key=(setup, round(float(a["frequency_hz"]), 9), int(a.get("repeat", 0))),
                status=STATUS_COMPLETE if status in STATUS_COMPLETE_ALIASES else status,
                quality_ok=a.get("quality_ok"))
            displacement = g.get("displacement", {})
            echoes = g.get("echoes", {})
            for ch in sorted(k for k in echoes if not k.endswith("_trigger_offset_s")):
                # on the displacement; on the echoes for a channel whose tracking failed
                qa = displacement[ch].attrs if ch in displacement else echoes[ch].attrs
                step.channels.append(_ChannelAtAGlance(ch, {
                    k: qa[f"quality_{k}"] for k in QUALITY_KEYS if f"quality_{k}" in qa}))
        except Exception:  # a group cut short by a kill: counted, as the reader does
            damaged += 1
            continue
        steps.append(step)
    return steps, damaged


def _quality_ok(step: _StepAtAGlance) -> bool:
    if step.quality_ok is None:
        return all(bool(c.quality.get("ok", True)) for c in step.channels)
    return bool(step.quality_ok)


def _complex_text(value: Any) -> list[float] | None:
    """A complex constant as [re, im] (JSON has no complex), None when absent or NaN."""
    if value is None:
        return None
    z = complex(np.asarray(value).reshape(-1)[0])
    return None if not np.isfinite(z) else [z.real, z.imag]
