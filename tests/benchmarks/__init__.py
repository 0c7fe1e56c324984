"""Benchmarks (``make bench``): speed and accuracy figures, never timed unit tests.

Every ``bench_*.py`` module here defines ``run() -> list[Result]``. Timings are printed as
ratios against a baseline measured in the same run on the same machine (the machines are
shared and noisy, so absolute seconds alone mean little).
"""
