"""A protocol's own [points]: positions no pelvis has are refused as the unit slip they are,
and a refused entry is reported once, by its own key (audit: ``position_m = [-93.0, 0.0,
30.0]``, millimetres in a metres field, passed the check and ``run`` said "session complete:
2 of 2 steps" with every FRF line NaN; a bad ``direction`` also drew "unknown point
'probe'" for each setup using it)."""

from __future__ import annotations

import math

import pytest

from pelvislab.acquisition.protocol import load_landmarks
from pelvislab.app.cli import main
from tests.test_protocol_schema import base, parse, problems_of

PROBE = """\
schema = "pelvislab-protocol"
schema_version = 1
name = "probe"
[sweep]
frequencies_hz = [80.0, 180.0]
drive_vpp = 0.2
periods_per_step = 10
[points.probe]
bone = "innominate_right"
POSITION
direction = [-1.0, 0.0, 0.0]
[[setups]]
name = "a"
excitation = "SIAS_R_x"
transducers = { ch1 = "probe" }
"""


def test_millimetres_in_position_m_are_refused_before_anything_runs(tmp_path, capsys):
    path = tmp_path / "probe.toml"
    path.write_text(PROBE.replace("POSITION", "position_m = [-93.0, 0.0, 30.0]"))
    assert main(["protocol", "check", str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert err.startswith(f"pelvislab protocol check: error: {path}: "
                          "points.probe.position_m: [-93, 0, 30] is 97.7 m from the model "
                          "origin")
    # says metres and what was meant
    assert ("position_m is in metres, so if these are millimetres write position_m = "
            "[-0.093, 0, 0.03] or position_mm = [-93, 0, 30]") in err
    assert "unknown point" not in err
    out = tmp_path / "probe.h5"
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 1
    assert "points.probe.position_m" in capsys.readouterr().err and not out.exists()
    # the same point in millimetres, or in metres, is fine
    for position in ("position_mm = [-93.0, 0.0, 30.0]", "position_m = [-0.093, 0.0, 0.03]"):
        path.write_text(PROBE.replace("POSITION", position))
        assert main(["protocol", "check", str(path)]) == 0
    capsys.readouterr()


def test_the_limit_is_far_outside_the_landmark_catalogue():
    from pelvislab.acquisition.protocol import MAX_POINT_DISTANCE_M

    farthest = max(math.dist(pt.position_m, (0.0, 0.0, 0.0))
                   for pt in load_landmarks().values())
    assert farthest < 0.2 < MAX_POINT_DISTANCE_M  # the catalogue: within 0.16 m
    data = base()
    data["points"] = {"far": {"bone": "", "position_mm": [1200.0, 0.0, 0.0],
                              "direction": [0.0, 0.0, 1.0]}}
    data["setups"][0]["transducers"]["ch2"] = "far"
    message = problems_of(data)
    assert "points.far.position_mm: [1200, 0, 0] is 1.2 m from the model origin" in message
    assert "millimetres typed" not in message  # position_mm is millimetres already
    data["points"]["far"]["position_mm"] = [990.0, 0.0, 0.0]
    assert parse(data).points["far"].position_m == pytest.approx((0.99, 0.0, 0.0))


def test_metres_typed_into_position_mm_on_a_bone_are_refused_saying_so():
    from pelvislab.acquisition.protocol import MIN_BONE_POINT_DISTANCE_M

    nearest = min(math.dist(pt.position_m, (0.0, 0.0, 0.0))
                  for pt in load_landmarks().values() if pt.bone)
    assert MIN_BONE_POINT_DISTANCE_M < 0.1 < nearest  # the catalogue: 115 mm and more
    data = base()
    data["points"] = {"slip": {"bone": "sacrum", "position_mm": [-0.135, 0.0, -0.01],
                               "direction": [-1.0, 0.0, 0.0]}}
    data["setups"][0]["transducers"]["ch2"] = "slip"
    message = problems_of(data)
    assert ("points.slip.position_mm: [-0.135, 0, -0.01] is 0.135 mm from the model origin"
            in message)
    assert ("if these are metres write position_mm = [-135, 0, -10] or position_m = "
            "[-0.135, 0, -0.01]") in message
    data["points"]["slip"]["position_mm"] = [-135.0, 0.0, -10.0]
    assert parse(data).points["slip"].position_m == pytest.approx((-0.135, 0.0, -0.01))
    # a point of no bone (a phantom's, a bed's) may sit at the origin
    data["points"]["slip"].update(bone="", position_mm=[0.0, 0.0, 0.0])
    assert parse(data).points["slip"].position_m == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("entry, key", [
    ({"bone": "", "position_m": [0.0, 0.0, 0.0], "direction": [-1.0, 0.0, 1.0]},
     "points.probe.direction"),
    ({"bone": "", "position_m": [0.0, 0.0, 0.0]}, "points.probe.direction"),
    ({"bone": "femur", "position_m": [0.0, 0.0, 0.0], "direction": [0.0, 0.0, 1.0]},
     "points.probe.bone"),
    ({"bone": "", "position_m": [-93.0, 0.0, 30.0], "direction": [0.0, 0.0, 1.0]},
     "points.probe.position_m"),
    ("not a table", "points.probe"),
])
def test_a_refused_point_is_reported_once_not_again_as_unknown(entry, key):
    data = base()
    data["points"] = {"probe": entry}
    data["setups"][0]["transducers"]["ch2"] = "probe"
    data["setups"][0]["excitation"] = "probe"
    message = problems_of(data)
    assert "unknown point" not in message
    problems = message.split(": ", 1)[1].split("; ")
    assert len(problems) == 1 and problems[0].startswith(f"{key}: "), problems


@pytest.mark.parametrize(("bone", "position", "key", "text"), [
    ("innominate_right", {"position_m": [0.0, 0.1, 0.0]}, "points.probe.position_m",
     "y = 0.1 m is on the subject's left"),
    ("innominate_left", {"position_mm": [-55.0, -125.0, 5.0]}, "points.probe.position_mm",
     "y = -125 mm is on the subject's right"),
])
def test_an_innominate_point_on_the_other_side_is_refused(bone, position, key, text):
    # a right-innominate point typed with y > 0 passed: its FRFs were the right bone's
    # motion computed at a place on the left (design 4.1: +y to the subject's left)
    data = base()
    data["points"] = {"probe": {"bone": bone, **position, "direction": [1.0, 0.0, 0.0]}}
    data["setups"][0]["transducers"]["ch2"] = "probe"
    message = problems_of(data)
    assert f"{key}: {text}" in message and "flip the sign of y" in message, message
    assert "unknown point" not in message


def test_innominate_points_at_the_symphysis_and_the_catalogue_pass():
    data = base()
    data["points"] = {
        "sym_r": {"bone": "innominate_right", "position_mm": [0.0, 5.0, -95.0],
                  "direction": [1.0, 0.0, 0.0]},
        "sym_l": {"bone": "innominate_left", "position_mm": [-10.0, -5.0, -100.0],
                  "direction": [1.0, 0.0, 0.0]},
        "mid": {"bone": "sacrum", "position_mm": [-150.0, -40.0, -55.0],
                "direction": [-1.0, 0.0, 0.0]}}
    data["setups"][0]["transducers"] = {"ch1": "sym_r", "ch2": "sym_l"}
    parse(data)
    catalogue = load_landmarks()
    for point in catalogue.values():
        if point.bone == "innominate_right":
            assert point.position_m[1] < 0
        elif point.bone == "innominate_left":
            assert point.position_m[1] > 0


def test_a_point_without_bone_is_warned_about_not_refused():
    # without `bone` a point was silently on no modelled bone ("") and the model-based
    # analyses left it out unsaid
    data = base()
    data["points"] = {"probe": {"position_mm": [-150.0, 0.0, -40.0],
                                "direction": [-1.0, 0.0, 0.0]}}
    data["setups"][0]["transducers"]["ch2"] = "probe"
    p = parse(data)
    assert p.points["probe"].bone == ""
    assert [w for w in p.warnings if w.startswith("points.probe.bone: not given")]
    data["points"]["probe"]["bone"] = ""
    assert not [w for w in parse(data).warnings if w.startswith("points.")]


def test_a_point_named_like_a_landmark_elsewhere_is_warned_about():
    # [points.SIAS_R_x] on the sacrum, 230 mm from the landmark, replaced it unsaid: the
    # session carried another place under the landmark's name
    data = base()  # its catalogue: b = innominate_left at (0, 0.11, 0), direction +x
    data["points"] = {"b": {"bone": "sacrum", "position_m": [-0.15, 0.0, -0.05],
                            "direction": [-1.0, 0.0, 0.0]}}
    p = parse(data)
    assert p.points["b"].bone == "sacrum"  # the protocol's own point still wins
    (note,) = [w for w in p.warnings if w.startswith("points.b:")]
    assert "replaces the catalogue landmark" in note
    assert "bone 'innominate_left' -> 'sacrum'" in note and "direction turned 180 deg" in note
    # a subject's own coordinates within the catalogue's uncertainty: no warning
    data["points"] = {"b": {"bone": "innominate_left", "position_m": [0.01, 0.12, 0.005],
                            "direction": [0.97, 0.24, 0.0]}}
    assert not [w for w in parse(data).warnings if w.startswith("points.")]
