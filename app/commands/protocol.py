"""``pelvislab protocol check``: validate a protocol file and estimate its duration."""

from __future__ import annotations

import argparse
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``protocol`` to the CLI."""
    p = subparsers.add_parser("protocol", help="protocol file tools")
    sub = p.add_subparsers(dest="protocol_command", metavar="ACTION")
    sub.required = True
    c = sub.add_parser("check", help="validate a protocol file and print its estimated duration",
                       description="Validate a protocol (schema pelvislab-protocol v1, "
                       "docs/protocols.md) against the bench limits and what its instruments' "
                       "drivers accept; print the plan, the "
                       "estimated duration and any warnings. Exit 1 with a one-line reason "
                       "naming each offending key when it is invalid.")
    c.add_argument("file", metavar="FILE", help="protocol file (TOML)")
    c.add_argument("--bench", metavar="BENCH.toml", help="bench file whose limits and "
                   "instruments apply (default: the simulated bench)")
    c.add_argument("--strict", action="store_true", help="treat warnings as errors (exit 1)")
    c.set_defaults(handler=check_command)


def check_command(args: argparse.Namespace) -> int:
    """Print the plan summary and warnings; invalid files raise a one-line error."""
    from pelvislab.acquisition.protocol import BenchLimits, load_protocol
    from pelvislab.acquisition.runner import speed_of_sound_note
    from pelvislab.drivers.bench import BenchConfig

    config = BenchConfig.load(args.bench) if args.bench else BenchConfig.default()
    protocol = load_protocol(args.file, BenchLimits.from_config(config))
    print(protocol.summary())
    replaced = speed_of_sound_note(config, protocol)
    if replaced:
        print(f"note: {replaced}", file=sys.stderr)
    for warning in protocol.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    if args.strict and protocol.warnings:
        print(f"pelvislab protocol check: {len(protocol.warnings)} warning(s) with --strict",
              file=sys.stderr)
        return 1
    print("ok")
    return 0
