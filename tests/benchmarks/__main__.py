"""Run every ``bench_*`` module in this folder and print its figures."""

from __future__ import annotations

import importlib
import pkgutil
import sys

import pelvislab.tests.benchmarks as package


def main() -> int:
    """Run all benchmarks (or those whose module name contains argv[1])."""
    pattern = sys.argv[1] if len(sys.argv) > 1 else ""
    names = sorted(
        m.name for m in pkgutil.iter_modules(package.__path__)
        if m.name.startswith("bench_") and pattern in m.name
    )
    if not names:
        print("no benchmarks yet")
        return 0
    for name in names:
        module = importlib.import_module(f"{package.__name__}.{name}")
        print(f"== {name}: {(module.__doc__ or '').strip().splitlines()[0]}", flush=True)
        for result in module.run():
            print("  " + result.row(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
