"""Identification (issue 8): recovery rates per perturbation bin, wall time, version B, noise.

Every figure is measured here, on the appendix E model with the face-up layout of table 6.3
(5-300 Hz at 2.5 Hz, all 18 parameters free), runs in a 2-process pool with one BLAS
thread per process (the machine's other load is included in the wall times).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pelvislab.model.studies import bins_runs, ch7_runs, make_executor, run_all
from pelvislab.tests.benchmarks.harness import Result


def run() -> list[Result]:
    """Benchmark rows (see module docstring)."""
    ours = bins_runs((0.1, 0.2, 0.3, 0.4), n_sets=10)
    plain = [replace(r, strategy="plain", label="plain " + r.label)
             for r in bins_runs((0.1, 0.4), n_sets=10)]
    version_b = [r for r in ch7_runs() if r.version_b]
    noise = [replace(r, position_mm=2.0, orientation_deg=10.0, label="noise " + r.label)
             for r in bins_runs((0.1, 0.2, 0.3), n_sets=10)]
    with make_executor(2) as pool:
        out = run_all(ours + plain + version_b + noise, pool)
    o_ours = out[:len(ours)]
    o_plain = out[len(ours):len(ours) + len(plain)]
    o_b = out[len(ours) + len(plain):len(ours) + len(plain) + len(version_b)]
    o_noise = out[len(ours) + len(plain) + len(version_b):]
    rows: list[Result] = []
    for dp in (0.1, 0.2, 0.3, 0.4):
        sel = [o for o in o_ours if o.run.dp == dp]
        ok = 100.0 * np.mean([o.max_error < 1e-3 for o in sel])
        base = [o for o in o_plain if o.run.dp == dp]
        if base:
            rows.append(Result(f"plain log residual, one start: success dp={dp:.0%}",
                               100.0 * np.mean([o.max_error < 1e-3 for o in base]), "%"))
        rows.append(Result(f"continuation strategy: success dp={dp:.0%} (all 18 within 0.1 %)",
                           ok, "%", target="100 %"))
    wall = [o.wall_time_s for o in o_ours]
    cpu = [o.cpu_time_s for o in o_ours]
    rows.append(Result("median wall time of one 18-parameter identification",
                       float(np.median(wall)), "s", target="<= 10 s"))
    rows.append(Result("max wall time of one 18-parameter identification",
                       float(np.max(wall)), "s"))
    rows.append(Result("median CPU time of one 18-parameter identification",
                       float(np.median(cpu)), "s"))
    rows.append(Result("median starts used", float(np.median([o.starts for o in o_ours])), ""))
    rows.append(Result("version B: ch. 7 cases recovered (f_k, f_c, 18 params within 0.1 %)",
                       float(sum(o.max_error < 1e-3 for o in o_b)), "of 7", target="7 of 7"))
    k_err = np.array([np.abs(o.rel_error[3:15]) for o in o_noise]) * 100
    m_err = np.array([np.abs(o.rel_error[0:3]) for o in o_noise]) * 100
    rows.append(Result("noise (2 mm + 10 deg): median |stiffness error|",
                       float(np.median(k_err)), "%", target="<= 15-30 % (thesis 30-60 %)"))
    rows.append(Result("noise (2 mm + 10 deg): 90th pct |stiffness error|",
                       float(np.percentile(k_err, 90)), "%"))
    rows.append(Result("noise (2 mm + 10 deg): median |mass error|",
                       float(np.median(m_err)), "%", target="thesis < 2.5-7 %"))
    return rows
