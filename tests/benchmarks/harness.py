"""Shared helpers for the benchmarks: best-of-N timing and the printed result rows."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Result:
    """One benchmark figure; ``ratio`` = baseline / measured for timings (> 1 is faster)."""

    name: str
    value: float
    unit: str
    baseline: float | None = None
    baseline_name: str = ""
    target: str = ""

    @property
    def ratio(self) -> float | None:
        """Baseline over measured value (speed-up), when a baseline exists."""
        if self.baseline is None or self.value == 0:
            return None
        return self.baseline / self.value

    def row(self) -> str:
        """A printable line for this result."""
        text = f"{self.name:<58} {self.value:12.4g} {self.unit:<8}"
        if self.ratio is not None:
            text += f"  x{self.ratio:8.2f} vs {self.baseline_name}"
        if self.target:
            text += f"  [target: {self.target}]"
        return text


def best_time_s(func: Callable[[], object], repeat: int = 5, number: int = 1) -> float:
    """Best-of-``repeat`` wall time of ``number`` calls, in seconds per call."""
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        for _ in range(number):
            func()
        best = min(best, (time.perf_counter() - start) / number)
    return best
