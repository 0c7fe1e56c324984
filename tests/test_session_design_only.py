"""A session written from design 4.2 alone re-processes: its /steps are self-describing.

A contract audit (session 40) wrote sessions with only the attributes design 4.2 lists
(point names, no bone/position/direction; int16 echoes; no /frf) and a step status of
"completed" (the design names the attribute, not its values). `reprocess` refused both:
"channel directions must be unit vectors (norms [nan nan ...])" and "holds no complete
step to reprocess (3 damaged or incomplete)".
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from pelvislab.acquisition.session import SessionReader
from pelvislab.tests.test_resume_finished import _finished

DESIGN_STEP_ATTRS = ("setup", "frequency_hz", "input", "started_at_s", "status")
DESIGN_ECHO_ATTRS = ("sample_rate_hz", "prf_hz", "delay_s", "volts_per_count", "volts_offset",
                     "speed_of_sound_m_s", "output")


def _design_only_copy(source, target, status="completed", rename=None):
    """``source``'s steps with design 4.2's attributes only, echoes as int16 (x256), no
    /frf; ``rename`` maps point names (to one the catalogue does not know)."""
    rename = rename or {}
    with h5py.File(source, "r") as src, h5py.File(target, "w") as out:
        out.attrs.update({"schema": "pelvislab-session", "schema_version": 1,
                          "created_utc": "2026-11-27T00:00:00Z", "software_version": "x"})
        out.create_group("protocol").attrs["toml"] = "a record, not an input"
        out.create_group("bench").attrs["simulated"] = True
        steps = out.create_group("steps")
        for name, g in src["steps"].items():
            step = steps.create_group(name)
            for key in DESIGN_STEP_ATTRS:
                step.attrs[key] = g.attrs[key]
            step.attrs["input"] = rename.get(str(g.attrs["input"]), str(g.attrs["input"]))
            step.attrs["status"] = status
            echoes = step.create_group("echoes")
            for ch, ds in g["echoes"].items():
                if ch.endswith("_trigger_offset_s"):
                    echoes.create_dataset(ch, data=ds[()])
                    continue
                codes = echoes.create_dataset(ch, data=ds[()].astype(np.int16) * 256)
                for key in DESIGN_ECHO_ATTRS:
                    codes.attrs[key] = ds.attrs[key]
                codes.attrs["volts_per_count"] = ds.attrs["volts_per_count"] / 256
                codes.attrs["output"] = rename.get(str(ds.attrs["output"]),
                                                   str(ds.attrs["output"]))
            step.create_dataset("force_phasor_n", data=g["force_phasor_n"][()])


def test_a_design_only_session_reprocesses_to_the_same_frf(tmp_path):
    from pelvislab.app.cli import main

    _, original = _finished(tmp_path)  # the simulated bench, 3 steps, SIAS_R_x and sacrum_x
    foreign = tmp_path / "foreign.h5"
    _design_only_copy(original, foreign)
    out = tmp_path / "re.h5"
    assert main(["reprocess", str(foreign), "--out", str(out)]) == 0
    with SessionReader(original) as a, SessionReader(out) as b:
        fa, fb = a.frf(), b.frf()
        step = next(b.steps(with_echoes=False))
    assert fb.outputs.name == fa.outputs.name and fb.inputs.name == fa.inputs.name
    # geometry from the landmark catalogue, the input's force into the surface as a run's
    np.testing.assert_allclose(fb.outputs.position_m, fa.outputs.position_m)
    np.testing.assert_allclose(fb.outputs.direction, fa.outputs.direction)
    np.testing.assert_allclose(fb.inputs.direction, fa.inputs.direction)
    assert list(fb.outputs.bone) == list(fa.outputs.bone)
    assert step.status == "complete"
    measured = np.isfinite(fa.H)
    assert measured.sum() >= 4 and np.array_equal(np.isfinite(fb.H), measured)
    np.testing.assert_allclose(fb.H[measured], fa.H[measured], rtol=1e-6)


def test_points_the_catalogue_does_not_know_and_unknown_statuses_are_named(tmp_path):
    from pelvislab.acquisition.runner import reprocess_session

    _, original = _finished(tmp_path)
    unknown = tmp_path / "unknown.h5"
    _design_only_copy(original, unknown, rename={"sacrum_x": "bed_frame_z"})
    with pytest.raises(ValueError, match=r"point\(s\) \['bed_frame_z'\] have no position or "
                                         "direction"):
        reprocess_session(unknown, tmp_path / "u.h5")
    queued = tmp_path / "queued.h5"
    _design_only_copy(original, queued, status="queued")
    with pytest.raises(ValueError, match="holds no complete step to reprocess \\(3 with status "
                                         "'queued'; a complete step has status 'complete'"):
        reprocess_session(queued, tmp_path / "q.h5")
    # no status attribute at all: the reader's 'incomplete' is not the file's word
    bare = tmp_path / "bare.h5"
    _design_only_copy(original, bare)
    with h5py.File(bare, "a") as handle:
        for step in handle["steps"].values():
            del step.attrs["status"]
    with pytest.raises(ValueError, match="\\(3 without a status attribute \\(cut short\\); "
                                         "a complete step has status 'complete', or "
                                         "completed, done"):
        reprocess_session(bare, tmp_path / "b.h5")
    assert not (tmp_path / "u.h5").exists() and not (tmp_path / "q.h5").exists()


def bed_frame_copy(original, path, bone=None):
    """``original`` as a design-only session (:func:`_design_only_copy`) whose sacrum_x is
    renamed bed_frame_z, a point the catalogue does not know, with its position and
    direction in the steps and ``output_bone`` only when ``bone`` is not None."""
    _design_only_copy(original, path, rename={"sacrum_x": "bed_frame_z"})
    with h5py.File(path, "a") as handle:
        for step in handle["steps"].values():
            for ds in step["echoes"].values():
                if ds.attrs.get("output") == "bed_frame_z":
                    ds.attrs["output_position_m"] = [0.0, 0.0, -0.3]
                    ds.attrs["output_direction"] = [0.0, 0.0, 1.0]
                    if bone is not None:
                        ds.attrs["output_bone"] = bone


def test_a_point_nothing_gives_a_bone_is_named_not_taken_as_off_bone(tmp_path):
    """A point outside the catalogue whose steps give its position and direction but no
    ``output_bone`` was written on no modelled bone without a word (identify and gap then
    leave it out as if deliberately off-bone); ``output_bone = ""``, as our writer puts it
    for an off-bone point, says so on purpose and is not flagged."""
    from pelvislab.acquisition.runner import reprocess_session

    _, original = _finished(tmp_path)
    for bone in (None, ""):
        path = tmp_path / f"bed_{bone is None}.h5"
        bed_frame_copy(original, path, bone)
        notes: list[str] = []
        out = tmp_path / f"re_{bone is None}.h5"
        reprocess_session(path, out, notes=notes)
        with SessionReader(out) as reader:
            frf, log = reader.frf(), reader.log_lines()
        assert frf.outputs.bone[frf.outputs.name.index("bed_frame_z")] == ""
        if bone is None:  # SIAS_R_x, in the catalogue, takes its bone from there: no note
            assert len(notes) == 1, notes
            assert notes[0].startswith("output point 'bed_frame_z' is not in the landmark "
                                       "catalogue (protocols/landmarks.toml)")
            assert "add output_bone" in notes[0]
            assert any(notes[0] in line for line in log), "the file's log says it too"
        else:
            assert notes == []
