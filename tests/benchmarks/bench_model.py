"""Model FRF synthesis and Jacobian speed (appendix E model, 18 DOF).

Figures: 28 FRFs (7 outputs x 4 inputs) x 1000 lines in one call, against a naive
per-line ``np.linalg.solve`` loop measured in the same run; FRF + full Jacobian at an
identification-sized problem (120 lines, 28 FRFs, 18 parameters) against central finite
differences with the same batched FRF. Run: ``make bench`` or
``.venv/bin/python -m pelvislab.tests.benchmarks model``.
"""

from __future__ import annotations

import numpy as np

from pelvislab.model.assembly import assemble
from pelvislab.model.frf import receptance, rows_for
from pelvislab.model.landmarks import landmark_points
from pelvislab.model.modal import complex_modes, modal_receptance
from pelvislab.model.parameters import parameter_space
from pelvislab.model.pelvis import default_model
from pelvislab.tests.benchmarks.harness import Result, best_time_s

OUTPUTS = ["sacrum_x", "SIAS_R_x", "SIAS_L_x", "SIAS_R_y", "SIAS_L_y", "SIPS_R_x", "SIPS_L_x"]
INPUTS = ["sacrum_x", "SIPS_R_x", "SIPS_L_x", "iliac_fossa_drive_L"]


def _naive(M, K, C, f, o, i):
    out = np.empty((f.size, o.shape[0], i.shape[0]), dtype=complex)
    for n, fn in enumerate(f):
        w = 2 * np.pi * fn
        x = np.linalg.solve(K - w * w * M + 1j * w * C, i.T)
        out[n] = o @ x
    return out


def run() -> list[Result]:
    model = default_model()
    s = assemble(model)
    o = rows_for(model, landmark_points(OUTPUTS))
    i = rows_for(model, landmark_points(INPUTS))
    results = []

    f = np.linspace(5.0, 300.0, 1000)
    naive = _naive(s.M, s.K, s.C, f, o, i)
    scale = np.abs(naive).max()
    for method in ("auto", "solve"):
        got = receptance(s.M, s.K, s.C, f, o, i, method=method)
        assert np.abs(got - naive).max() < 1e-9 * scale, method
    t_n = best_time_s(lambda: _naive(s.M, s.K, s.C, f, o, i), repeat=3)
    t_a = best_time_s(lambda: receptance(s.M, s.K, s.C, f, o, i), repeat=7)
    t_s = best_time_s(lambda: receptance(s.M, s.K, s.C, f, o, i, method="solve"), repeat=7)
    results.append(Result("FRF 28 x 1000 lines, receptance() default: lines/s", 1000 / t_a,
                          "lines/s"))
    results.append(Result("FRF 28 x 1000 lines, receptance() default (spectral): time", t_a,
                          "s", baseline=t_n, baseline_name="per-line solve loop"))
    results.append(Result("FRF 28 x 1000 lines, method='solve' (batched): time", t_s, "s",
                          baseline=t_n, baseline_name="per-line solve loop"))

    def modal_path() -> np.ndarray:
        return modal_receptance(complex_modes(s.M, s.K, s.C), f, o, i)

    assert np.abs(modal_path() - naive).max() < 1e-9 * scale
    t_m = best_time_s(modal_path, repeat=7)
    results.append(Result("FRF 28 x 1000 lines, modal.modal_receptance incl. eig: time", t_m,
                          "s", baseline=t_n, baseline_name="per-line solve loop"))

    space = parameter_space(model, symmetric=False)
    v = space.values()
    f120 = np.linspace(5.0, 300.0, 120)

    def jac() -> tuple[np.ndarray, np.ndarray]:
        return space.frf_and_jacobian(v, f120, o, i, scaled=True)

    def fd_jac() -> np.ndarray:
        cols = []
        for j in range(len(space)):
            vp, vm = v.copy(), v.copy()
            vp[j] *= 1 + 1e-6
            vm[j] *= 1 - 1e-6
            a, b = space.matrices(vp), space.matrices(vm)
            cols.append((receptance(a.M, a.K, a.C, f120, o, i, method="solve")
                         - receptance(b.M, b.K, b.C, f120, o, i, method="solve")) / 2e-6)
        return np.stack(cols, axis=-1)

    t_j = best_time_s(jac, repeat=7)
    t_fd = best_time_s(fd_jac, repeat=3)
    results.append(Result("FRF + Jacobian (120 lines, 28 FRFs, 18 params): time", t_j, "s",
                          baseline=t_fd, baseline_name="central FD with batched FRF"))
    results.append(Result("FRF + Jacobian evaluations per second", 1 / t_j, "calls/s"))
    return results


if __name__ == "__main__":
    for r in run():
        print(r.row())
