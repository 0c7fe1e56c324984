"""``pelvislab session info``: what a session or FRF-only file holds, at a glance."""

from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``session info`` to the CLI."""
    p = subparsers.add_parser("session", help="session file tools")
    sub = p.add_subparsers(dest="session_command", metavar="ACTION")
    sub.required = True
    i = sub.add_parser(
        "info", help="what a session or FRF-only file holds, at a glance",
        description="Summarise a session file (or an FRF-only file): subject and protocol, "
        "how each run ended and whether its outputs were confirmed off, the steps acquired "
        "against the protocol's plan per setup, tracking quality per channel, the /frf "
        "lines and points (H_std or not), and the log's warnings. Reads no raw echoes "
        "(--check reads every step's data).")
    i.add_argument("session", metavar="S.h5", help="session or FRF-only file")
    i.add_argument("--json", metavar="OUT",
                   help="also write the summary as JSON to this file; '-': print the JSON "
                   "alone on stdout instead of the text")
    i.add_argument("--check", action="store_true",
                   help="also read every step's data (raw echoes included) and report the "
                   "step groups that cannot be read whole: exit 1 when there is one (the "
                   "summary reads the steps' attributes only, so damaged data there pass "
                   "unseen)")
    i.set_defaults(handler=info_command)


def info_command(args: argparse.Namespace) -> int:
    """Print the summary (text, or JSON with ``--json -``); ``--json FILE`` also writes it."""
    from pelvislab.acquisition.session_info import session_info
    from pelvislab.app.commands._common import check_new_output, print_json, write_json

    if args.json not in (None, "-"):
        check_new_output(args.json)
    info = session_info(args.session)
    if args.check:
        info["check"] = check_steps(args.session) if info["kind"] != "frf-only" else None
    if args.json == "-":
        print_json(info)
        return 1 if info.get("check") and info["check"]["damaged"] else 0
    print(info_text(info))
    check = info.get("check")
    if check is not None:
        print(f"check: {check['read_whole']} step group(s) read whole"
              + (f", {len(check['damaged'])} damaged:" if check["damaged"] else
                 ", none damaged"))
        for problem in check["damaged"]:
            print(f"  {problem}")
        if check["damaged"]:
            print("  `run --resume` measures such a step again unless a later group holds "
                  "it; `reprocess` and the analyses leave it out")
    if args.json:
        print(f"JSON: {write_json(args.json, info)}")
    return 1 if check and check["damaged"] else 0


def check_steps(path: str) -> dict[str, Any]:
    """Read every step group whole (raw echoes, displacement, phasors): how many read and
    which could not be (the summary reads the steps' attributes only: a damaged echoes
    chunk passed as "8 acquired of 8", found by a review in session 50)."""
    from pelvislab.acquisition.session import SessionReader

    with SessionReader(path) as reader:
        n = sum(1 for _ in reader.steps(include_incomplete=True, with_echoes=True))
        return {"read_whole": n, "damaged": list(reader.damaged)}


def info_text(info: dict[str, Any]) -> str:
    """The summary of :func:`~pelvislab.acquisition.session_info.session_info` as text."""
    lines = [f"{info['file']}: {info['kind']} ({info['schema']})"]
    if info["kind"] != "frf-only":
        who = ", ".join(x for x in (
            f"subject {info['subject_id']}" if info["subject_id"] else "no subject id",
            f"position {info['subject_position']}" if info["subject_position"] else "")
            if x)
        lines.append(f"protocol {info['protocol_name']!r}; {who}; created "
                     f"{info['created_utc']} (pelvislab {info['software_version']})")
        if info["reprocessed_from"]:
            lines.append(f"reprocessed from {info['reprocessed_from']}")
        lines.append(_status_line(info))
        # only against a known plan: a stored protocol that does not parse cannot be
        # resumed (run --resume needs a protocol file holding that very text)
        planned = info["steps"]["planned"]
        # no resume advice while its writer lives: two writers would corrupt the file
        if info["status"] != "completed" and planned is not None and \
                info["steps"]["acquired"] < planned and not info.get("writer_alive"):
            last = info["runs"][-1] if info["runs"] else {}
            # written elsewhere (NFS, file locking off): its writer may still run there
            once = (f", once process {last['pid']} on {last['host']} has ended"
                    if info["status"] == "running" and info.get("writer_alive") is None
                    and last.get("host") and last.get("pid") else "")
            if info["reprocessed_from"]:
                lines.append(f"  to complete it: resume its source session "
                             f"{info['reprocessed_from']} and reprocess that (a reprocessed "
                             "file is not resumed)")
            elif info["protocol_source_state"] == "matches":
                lines.append(f"  to complete it{once}: pelvislab run "
                             f"{info['protocol_source']} --out {info['file']} --resume")
            else:
                # resume refuses a protocol file whose text is not the stored one
                source = info["protocol_source"]
                why = {"missing": f"{source} is not found from here",
                       "differs": f"{source} differs from it: edited since the run?"}.get(
                    info["protocol_source_state"], "no protocol file is recorded")
                lines.append(f"  to complete it{once}: pelvislab run PROTOCOL.toml --out "
                             f"{info['file']} --resume, PROTOCOL.toml holding the "
                             f"session's /protocol text exactly ({why})")
        for run in info["runs"]:
            bench = {True: "simulated bench", False: "real bench", None: "bench ?"}[
                run["simulated"]]
            off = {True: "outputs off", False: "OUTPUTS NOT CONFIRMED OFF",
                   None: "outputs off not recorded"}[run["outputs_confirmed_off"]]
            reason = f" ({run['reason']})" if run["reason"] else ""
            if run["status"] == "running":
                reason = " (no end recorded)"
            lines.append(f"  run {run['index']}: {run['started_utc']} -> "
                         f"{run['ended_utc'] or '?'}: {run['status']}{reason}; {bench}; {off}")
        steps = info["steps"]
        planned = f" of {steps['planned']} planned" if steps["planned"] is not None else ""
        extra = [f"{steps[k]} {k.replace('_', ' ')}" for k in
                 ("incomplete", "damaged", "quality_not_ok") if steps[k]]
        lines.append(f"steps: {steps['acquired']} acquired{planned}"
                     + (f" ({', '.join(extra)})" if extra else ""))
        for s in steps["by_setup"]:
            chans = ", ".join(f"{c} {p}" for c, p in s["transducers"].items())
            bad = f", {s['quality_not_ok']} not ok" if s["quality_not_ok"] else ""
            lines.append(f"  {s['setup']}: drive at {s['excitation']}; {chans}: "
                         f"{s['acquired']}/{s['planned']}{bad}")
        for name, c in info["channels"].items():
            lost = ("lost echoes median "
                    f"{100 * c['lost_fraction_median']:.2g} %, max "
                    f"{100 * c['lost_fraction_max']:.2g} %"
                    if c["lost_fraction_median"] is not None else "lost echoes ?")
            snr = (f"SNR median {c['snr_db_median']:.1f} dB"
                   if c["snr_db_median"] is not None else "SNR ?")
            gates = ", ".join(f"{k} {v}" for k, v in c["gate_sources"].items())
            notes = f"; tracker notes on {c['tracker_notes']}" if c["tracker_notes"] else ""
            unknown = (f" ({c['quality_not_recorded']} without tracking quality)"
                       if c["quality_not_recorded"] else "")
            lines.append(f"  {name}: {c['records']} records, {c['quality_not_ok']} not ok"
                         f"{unknown}; {lost}; {snr}; gates: {gates}{notes}")
    frf = info.get("frf")
    if frf:
        span = (f"{frf['frequency_hz'][0]:g}-{frf['frequency_hz'][1]:g} Hz"
                if frf["frequency_hz"] else "no lines")
        step = ""
        if frf["spacing_hz"]:
            lo, hi = frf["spacing_hz"]
            step = f", spacing {lo:g} Hz" if np_isclose(lo, hi) else \
                f", spacing {lo:g}-{hi:g} Hz"
        planned = (f" of {frf['pairs_planned']} planned" if frf["pairs_planned"] is not None
                   else f" of {len(frf['outputs']) * len(frf['inputs'])} (output, input) cells")
        lines.append(f"/frf: {frf['lines']} lines {span}{step} ({frf['lines_with_data']} "
                     f"with data); {len(frf['outputs'])} outputs x {len(frf['inputs'])} "
                     f"inputs, {frf['pairs_measured']} pairs measured{planned}; H_std "
                     + ("given" if frf["h_std"] else NO_H_STD))
        bones = {p["name"]: p["bone"] or "no modelled bone" for p in frf["outputs"]}
        lines.append("  outputs: " + ", ".join(f"{n} ({b})" for n, b in bones.items()))
        bones = {p["name"]: p["bone"] or "no modelled bone" for p in frf["inputs"]}
        lines.append("  inputs: " + ", ".join(f"{n} ({b})" for n, b in bones.items()))
        # pairs short of lines; with a plan, also those planned and never measured (an
        # FRF-only file's empty cells are its layout, not a shortfall)
        planned_known = frf["pairs_planned"] is not None
        for p in frf["pairs"]:
            if 0 < p["lines_measured"] < frf["lines_with_data"] or (
                    planned_known and p["lines_measured"] == 0):
                lines.append(f"  {p['output']}/{p['input']}: {p['lines_measured']} of "
                             f"{frf['lines_with_data']} lines")
    log = info.get("log")
    if log:
        lines.append(f"log: {log['lines']} lines, {log['warnings']} warning(s), "
                     f"{log['errors']} error(s)")
        lines.extend(f"  {line}" for line in log["latest_flagged"])
    lines.extend(f"note: {n}" for n in info["notes"])
    return "\n".join(lines)


#: What the analyses do without H_std (as export-uff's note says).
NO_H_STD = ("absent (identify and gap diagnose estimate the noise; ema weights each FRF by "
            "1/RMS)")

#: What a "running" status means in a file that opens: no process holds it for writing.
KILLED = "no end recorded: the run's process ended without closing the file (killed?)"


def _status_line(info: dict[str, Any]) -> str:
    reason = f" ({info['reason']})" if info["reason"] else ""
    if info["status"] == "running":
        reason = f" ({KILLED})"
        last = info["runs"][-1] if info["runs"] else {}
        if info.get("writer_alive"):
            reason = (f" (no end recorded, and its process {last.get('pid')} on this host "
                      "is still running: being written, with HDF5 file locking off?)")
        elif info.get("writer_alive") is None and last.get("host"):
            reason = (f" (no end recorded: killed, unless its process {last.get('pid')} on "
                      f"{last['host']} is still running)")
    off = info["outputs_confirmed_off"]
    said = {True: "every run's outputs confirmed off",
            False: "OUTPUTS NOT CONFIRMED OFF in a run (see the runs below)",
            None: "outputs off not recorded"}[off]
    unrecorded = [str(r["index"]) for r in info["runs"] if r["outputs_confirmed_off"] is None]
    if off is True and unrecorded:
        # the reader's True counts the runs that recorded it: a killed run resumed later
        # had read "every run's outputs confirmed off" (review, session 43)
        said = (f"outputs confirmed off at the end of the runs that recorded it; not "
                f"recorded for run {', '.join(unrecorded)}")
    if info["status"] == "running" and off is not False:
        said += (" (the run is under way)" if info.get("writer_alive")
                 else " (a killed run may have left an output on: check the bench)")
    return f"status: {info['status']}{reason}; {said}"


def np_isclose(a: float, b: float) -> bool:
    """Whether two line spacings are the same grid step (to 1e-6 relative)."""
    return abs(a - b) <= 1e-6 * max(abs(a), abs(b))
