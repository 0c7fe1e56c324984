"""Cross-check of the model core against an independent reading of the thesis.

``tests/independent_pelvis.py`` re-implements the appendix-E pelvis model (thesis ch. 4.2,
5.2-5.4, appendix E) from the thesis text with numpy only. Here it is compared with
``pelvislab.model`` on (a) appendix E as is and (b) a perturbed subject (masses and
springs +-30 %, dashpot groups 10-3000 N s/m), at the face-up layout of table 6.3
(landmark catalogue; excitation force into the bone) plus arbitrary points, 5-300 Hz.

Finding: M and K agree to round-off; C agrees to round-off when both implementations
read the dashpots the same way. The product's default evaluates both bodies of a dashpot at
the midpoint of its two attachment points; the thesis (eq. 4.16, ch. 5.4, Fig. 5.6) takes
each body's velocity at its own attachment point, which the product reads with
``dashpot_lever = "points"``. The two readings differ only for dashpot S1, whose printed
innominate point (appendix E, (-79, -45, -0.2) mm) is not on the joint normal through its
sacral point, unlike S2 and S3 (0.7 mm along (2, -2, -1)/3).
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.acquisition.frfset import Channels
from pelvislab.model.assembly import assemble
from pelvislab.model.frf import frf
from pelvislab.model.landmarks import load_landmarks
from pelvislab.model.pelvis import default_model
from pelvislab.tests import independent_pelvis as ip

F_HZ = np.arange(5.0, 300.01, 1.5)
TOL = 1e-9

_CAT = load_landmarks()
_OUT = ["sacrum_x", "SIPS_R_x", "SIPS_L_x", "SIAS_R_x", "SIAS_L_x", "SIAS_R_y", "SIAS_L_y"]
_IN = ["sacrum_x", "SIPS_R_x", "SIPS_L_x"]


def _arbitrary_points(n=6, seed=11):
    rng = np.random.default_rng(seed)
    pts = []
    for i in range(n):
        bone = ip.BONES[i % 3]
        d = rng.normal(size=3)
        pts.append((f"arb{i}", bone, ip.CENTRE_OF_MASS[bone] + rng.uniform(-0.08, 0.08, 3),
                    d / np.linalg.norm(d)))
    return pts


_ARB = _arbitrary_points()
OUTPUTS = [(n, _CAT[n].bone, np.asarray(_CAT[n].position_m), np.asarray(_CAT[n].direction))
           for n in _OUT] + _ARB
INPUTS = [(n, _CAT[n].bone, np.asarray(_CAT[n].position_m), -np.asarray(_CAT[n].direction))
          for n in _IN] + _ARB[:3]


def _channels(points):
    return Channels([p[0] for p in points], [p[1] for p in points],
                    np.array([p[2] for p in points]), np.array([p[3] for p in points]))


def _case(name):
    """(product model, independent keyword arguments) for case ``name``."""
    model = default_model()
    if name == "appendix_e":
        return model, {}
    rng = np.random.default_rng(2024)
    mass_scale, stiffness, damping = {}, {}, {}
    for b in model.bodies:
        f = 1.0 + rng.uniform(-0.3, 0.3)
        model = model.with_mass(b.name, b.mass_kg * f)
        mass_scale[b.name] = f
    for s in model.springs:
        k = s.stiffness_n_per_m * (1.0 + rng.uniform(-0.3, 0.3))
        model = model.replace_spring(s.name, stiffness_n_per_m=k)
        stiffness[s.name] = k
    groups = {"R": 10 ** rng.uniform(1.0, np.log10(3000.0)),
              "L": 10 ** rng.uniform(1.0, np.log10(3000.0)),
              "": 10 ** rng.uniform(1.0, np.log10(3000.0))}
    for d in model.dashpots:
        model = model.replace_dashpot(d.name, coefficient_n_s_per_m=groups[d.side])
        damping[d.name] = groups[d.side]
    return model, {"mass_scale": mass_scale, "stiffness": stiffness, "damping": damping}


def _gap(h_product, h_indep):
    """Largest |difference| over frequencies and FRFs, relative to each FRF's peak."""
    return float((np.abs(h_product - h_indep) / np.abs(h_indep).max(axis=0)).max())


def _frfs(name, lever, damping_override=None, product_lever="midpoint"):
    model, kw = _case(name)
    model = model.with_dashpot_lever(product_lever)
    if damping_override:
        kw = {**kw, "damping": {**kw.get("damping", {}), **damping_override}}
        for dname, c in damping_override.items():
            model = model.replace_dashpot(dname, coefficient_n_s_per_m=c)
    h_p = frf(model, F_HZ, _channels(OUTPUTS), _channels(INPUTS))
    h_i = ip.frf(F_HZ, [p[1:] for p in OUTPUTS], [p[1:] for p in INPUTS],
                 dashpot_lever=lever, **kw)
    return h_p, h_i


CASES = ["appendix_e", "perturbed"]


def test_independent_reading_is_self_consistent():
    # 6 free-free rigid-body modes + 12 elastic (ch. 5.3), 8 dissipative directions
    # (ch. 5.4), sacral dashpot points on the plane 2x - 2y - z = -70 mm (to print precision)
    m, c, k = ip.matrices()
    f = ip.natural_frequencies()
    assert np.all(f[:6] < 1e-3) and np.all(f[6:] > 5.0)
    assert np.linalg.matrix_rank(c, tol=1e-12 * np.abs(c).max()) == 8
    assert ip.sij_plane_residual_mm() < 1e-3
    assert np.allclose(m, m.T) and np.allclose(k, k.T) and np.allclose(c, c.T)


@pytest.mark.parametrize("name", CASES)
def test_mass_stiffness_and_natural_frequencies_match(name):
    model, kw = _case(name)
    s = assemble(model)
    m, _, k = ip.matrices(kw.get("mass_scale"), kw.get("stiffness"), kw.get("damping"))
    assert np.abs(s.M - m).max() <= 1e-12 * np.abs(m).max()
    assert np.abs(s.K - k).max() <= 1e-12 * np.abs(k).max()
    lam = np.sort(np.linalg.eigvals(np.linalg.solve(s.M, s.K)).real)
    f_p = np.sqrt(np.clip(lam, 0.0, None)) / (2 * np.pi)
    f_i = ip.natural_frequencies(kw.get("mass_scale"), kw.get("stiffness"))
    np.testing.assert_allclose(f_p[6:], f_i[6:], rtol=TOL)


@pytest.mark.parametrize("name", CASES)
def test_frf_matches_with_midpoint_dashpot_levers(name):
    h_p, h_i = _frfs(name, "midpoint")
    assert _gap(h_p, h_i) < TOL


@pytest.mark.parametrize("name", CASES)
def test_literal_reading_differs_only_through_sacroiliac_dashpot_offsets(name):
    # The two lever readings coincide for a dashpot whose points are offset along its
    # normal: exactly so for the pubic dashpots (offset along y) ...
    off = {f"S{j}_{side}": 0.0 for j in (1, 2, 3) for side in "RL"}
    h_p, h_i = _frfs(name, "points", off)
    assert _gap(h_p, h_i) < TOL
    # ... and up to the three-decimal printing for S2/S3 (< 1 um off the normal); S1's
    # printed offset is 0.71 mm off it and carries the xfail'd difference below
    h_p, h_i = _frfs(name, "points", {"S1_R": 0.0, "S1_L": 0.0})
    assert _gap(h_p, h_i) < 1e-3


@pytest.mark.parametrize("name", CASES)
def test_frf_matches_thesis_literal_dashpot_levers(name):
    h_p, h_i = _frfs(name, "points", product_lever="points")
    assert _gap(h_p, h_i) < TOL
    # and the default (midpoint) reading is what differs: ~2e-4 of an FRF peak at
    # appendix E, up to ~5e-2 (at 5 Hz) with damping 10-3000 N s/m
    h_p, h_i = _frfs(name, "points")
    assert _gap(h_p, h_i) > 1e-4
