"""--resume of a session that already holds every step, a protocol gate the runner
refuses, resume's warnings and reprocess's progress: found by reviews of session 39's
commits and by its first-day review (each failed before its fix)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from pelvislab.acquisition.runner import NothingToResume, prepare_session
from pelvislab.acquisition.session import SessionReader
from pelvislab.tests.test_runner_aiming import PROTOCOL as AIM_PROTOCOL

sim_bench = pytest.importorskip("pelvislab.sim_instruments.bench")

# setup a of the live-echo tests' protocol: three steps, two channels
PROTOCOL = AIM_PROTOCOL.split("[[setups]]\nname = \"b\"")[0]


def _finished(tmp_path, text=PROTOCOL):
    protocol = tmp_path / "p.toml"
    protocol.write_text(text)
    out = tmp_path / "s.h5"
    with prepare_session(protocol, out, bench=sim_bench.open_simulated_bench(
            generators="python")) as session:
        assert session.run().status == "completed"
    return protocol, out


def test_a_protocol_gate_the_runner_refuses_leaves_no_session_file(tmp_path):
    """Runner.__init__ refuses a protocol gate its lag range cannot use "before anything
    runs", but prepare_session has created (and published) the session file by then: the
    same command again says 'exists; use --resume'."""
    from pelvislab.acquisition.tracking import TrackingOptions

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL.replace(
        'transducers = { ch1 = "SIAS_R_x", ch2 = "sacrum_x" }',
        'transducers = { ch1 = "SIAS_R_x", ch2 = "sacrum_x" }\ngates = { ch1 = [20, 404] }'))
    out = tmp_path / "s.h5"
    with pytest.raises(ValueError, match="gate"):
        prepare_session(protocol, out, bench=sim_bench.open_simulated_bench(
            generators="python"), tracking_options=TrackingOptions(max_lag_samples=30))
    assert not out.exists()


def test_resume_still_repairs_frf_after_a_kill_between_the_last_flush_and_its_lines(
        tmp_path):
    """A kill between append_step's flush and _write_frf_lines (the case repair_frf exists
    for) on the last step leaves every step complete and /frf without its lines. Resume
    repairs it, without a bench or a run record (NothingToResume had left /frf short for
    good, and the analyses read /frf)."""
    protocol, out = _finished(tmp_path)
    with SessionReader(out) as reader:
        steps = list(reader.steps(with_echoes=False))
        last = steps[-1]
    with h5py.File(out, "r+") as h5:
        freqs = h5["frf"]["frequency_hz"][()]
        i = int(np.argmin(np.abs(freqs - last.frequency_hz)))
        H = h5["frf"]["H"][()]
        H[i] = np.nan  # its lines never written: the kill
        h5["frf"]["H"][...] = H
    with h5py.File(out, "r") as h5:
        runs_before = len(h5["runs"])
    with pytest.raises(NothingToResume, match="/frf was rebuilt from its steps") as raised:
        prepare_session(protocol, out, resume=True, bench=None)
    assert "missing: lost to a kill" in str(raised.value)
    assert "differed" not in str(raised.value)
    with SessionReader(out) as reader:
        assert np.isfinite(reader.frf().H[i]).any(), "the last step's /frf lines are lost"
        assert len(reader.handle["runs"]) == runs_before
    with pytest.raises(NothingToResume, match="the file is left as it is"):
        prepare_session(protocol, out, resume=True, bench=None)


def test_a_finished_session_that_once_had_a_cut_step_is_left_as_it_is(tmp_path):
    """A step cut short by a kill and measured again on resume stays in the file as an
    incomplete group. Every planned step is then kept, yet that group made a further
    --resume open the bench, append a run record and log 'measured again' for a step it
    does not measure: what NothingToResume is for."""
    protocol, out = _finished(tmp_path)
    with h5py.File(out, "r+") as h5:
        steps = h5["steps"]
        first = sorted(n for n in steps if n.isdigit())[0]
        h5.copy(steps[first], steps, name=f"{9:06d}")
        steps[f"{9:06d}"].attrs["status"] = "incomplete"
        runs_before = len(h5["runs"])
    with pytest.raises(NothingToResume):
        prepare_session(protocol, out, resume=True, bench=sim_bench.open_simulated_bench(
            generators="python")).close()
    with h5py.File(out, "r") as h5:
        assert len(h5["runs"]) == runs_before


def test_gui_nothing_to_continue_keeps_the_replay_of_that_file(operator_window, qtbot,
                                                               tmp_path, monkeypatch):
    """Start on a finished session shown in the replay: start_run closes the replay's
    reader (HDF5 opens a file once) before SessionControl raises NothingToResume; the
    'Nothing to continue' path returned without opening it again and the replay went
    blank (helper review, session 39)."""
    from PySide6 import QtWidgets

    from pelvislab.app import gui_main

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    out = tmp_path / "s.h5"
    with prepare_session(protocol, out, bench=sim_bench.open_simulated_bench(
            generators="python"), subject_id="T001") as session:
        assert session.run().status == "completed"
    said = []
    monkeypatch.setattr(gui_main, "alert", lambda parent, title, text, critical=True:
                        said.append(title))
    monkeypatch.setattr(QtWidgets.QMessageBox, "question",
                        lambda *args, **kwargs: QtWidgets.QMessageBox.StandardButton.Yes)
    window = operator_window()
    window.protocol_combo.addItem("review39b", str(protocol))
    window.protocol_combo.setCurrentIndex(window.protocol_combo.count() - 1)
    window.subject_edit.setText("T001")
    window.out_edit.setText(str(out))
    window.replay.open_session(out)
    window.start_run()
    assert said == ["Nothing to continue"], said
    assert window.replay.path == out and window.replay.reader is not None


def test_resume_warns_only_of_cut_steps_it_measures_again(tmp_path):
    """A group cut short whose step is complete elsewhere in the file was announced as
    'measured again' on every resume (helper review, session 39); one whose step is
    missing is measured again, and said."""
    protocol, out = _finished(tmp_path)
    with h5py.File(out, "r+") as h5:
        steps = h5["steps"]
        names = sorted(n for n in steps if n.isdigit())
        h5.copy(steps[names[0]], steps, name="000010")  # its step is complete: history
        steps["000010"].attrs["status"] = "incomplete"
        h5.copy(steps[names[-1]], steps, name="000011")  # its step is gone: measured again
        steps["000011"].attrs["status"] = "incomplete"
        del steps[names[-1]]
    with prepare_session(protocol, out, resume=True, bench=sim_bench.open_simulated_bench(
            generators="python")) as session:
        assert session.run().status == "completed"
    with SessionReader(out) as reader:
        lines = reader.log_lines()
        assert len(list(reader.steps(with_echoes=False))) == 3
    said = [line for line in lines if "measured again" in line]
    assert any("000011" in line for line in said), said
    assert not any("000010" in line for line in said), said


def test_reprocess_says_its_progress_without_a_terminal_when_asked(tmp_path, capsys):
    # 35 s of silence on a face_up session when stderr was a log (first-day review,
    # session 39): --progress prints a line about every tenth of the steps
    from pelvislab.app.cli import main

    _, out = _finished(tmp_path)
    assert main(["reprocess", str(out), "--out", str(tmp_path / "r.h5"), "--progress"]) == 0
    err = capsys.readouterr().err
    assert "reprocessing step 3/3" in err and "reprocessed 3 steps" in err
    assert main(["reprocess", str(out), "--out", str(tmp_path / "q.h5")]) == 0
    assert "reprocessing step" not in capsys.readouterr().err


def test_a_stored_value_that_differs_from_its_step_is_not_blamed_on_a_kill(tmp_path):
    """A /frf value that differs from its step (here /frf changed; a damaged phasor gives
    the same) was rebuilt with "lines lost to a kill" (review, session 50): the resume now
    says that values differed and that the cause may be damage."""
    protocol, out = _finished(tmp_path)
    with h5py.File(out, "r+") as h5:
        H = h5["frf"]["H"][()]
        k = np.argwhere(np.isfinite(H))[0]
        H[tuple(k)] *= 1.5
        h5["frf"]["H"][...] = H
    with pytest.raises(NothingToResume, match="/frf was rebuilt from its steps") as raised:
        prepare_session(protocol, out, resume=True, bench=None)
    assert "1 value(s) that differed from the steps" in str(raised.value)
    assert "missing" not in str(raised.value)
    with SessionReader(out) as reader:
        assert any("differed from the steps" in line for line in reader.log_lines())


def test_a_changed_protocol_is_refused_naming_the_first_line_that_differs(tmp_path):
    """"its /protocol differs" did not say where, and a comment edited counts (the session
    keeps the very text it was measured with; review, session 50)."""
    protocol, out = _finished(tmp_path)
    text = protocol.read_text().splitlines()
    k = next(i for i, line in enumerate(text) if line.startswith("name = "))
    text[k] += "  # edited"
    protocol.write_text("\n".join(text) + "\n")
    with pytest.raises(ValueError, match=rf"line {k + 1}: .*# edited' in the file"):
        prepare_session(protocol, out, resume=True, bench=None)
