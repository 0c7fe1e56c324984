"""Agilent 33220A driver: exact command strings, limits, error queue, safe state; and the
same driver through pyvisa-sim with sim_instruments/agilent_33220a.yaml."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pelvislab.drivers import agilent33220a as ag
from pelvislab.drivers.agilent33220a import Agilent33220A, ReferenceUnlockedError
from pelvislab.drivers.bench import Bench, BenchConfig
from pelvislab.drivers.interfaces import (
    DriverError,
    Generator,
    InstrumentConnectionError,
    InstrumentError,
    InstrumentTimeoutError,
    LimitError,
)
from pelvislab.drivers.scpi import ScriptedTransport, VisaTransport

OK = '+0,"No error"'
IDN = "Agilent Technologies,33220A,MY44000001,2.02-2.02-22-2"
YAML = Path(__file__).resolve().parents[1] / "sim_instruments" / "agilent_33220a.yaml"
SIM = f"{YAML}@sim"
RES1 = "USB0::0x0957::0x0407::MY44000001::INSTR"
RES2 = "USB0::0x0957::0x0407::MY44000002::INSTR"


def open_script(load="50", option001=True):
    s = [("*IDN?", IDN), ("*RST", None), ("*CLS", None), ("SYST:ERR?", OK), ("*OPC?", "1"),
         ("OUTP OFF", None), ("VOLT:UNIT VPP", None), (f"OUTP:LOAD {load}", None),
         ("SYST:ERR?", OK), ("PHAS:UNL:ERR:STAT ON", None)]
    if option001:
        s += [("SYST:ERR?", OK)]
    else:
        s += [("SYST:ERR?", '-113,"Undefined header"'), ("SYST:ERR?", OK)]
    return s


def make(extra, load=50.0, max_vpp=None, option001=True):
    load_tok = "INF" if math.isinf(load) else f"{load:g}"
    t = ScriptedTransport(open_script(load_tok, option001) + extra)
    g = Agilent33220A(t, "FAKE::INSTR", load_ohm=load, max_vpp=max_vpp)
    return g, t


# ---------------------------------------------------------------- exact protocol
def test_open_sequence_and_identity():
    g, t = make([])
    t.assert_done()
    assert g.identity == IDN
    assert g.has_option_001 is True
    # structural conformance (isinstance on a runtime Protocol would evaluate the
    # output_enabled property, i.e. send OUTP?, on Python 3.11)
    for name in Generator.__protocol_attrs__ if hasattr(Generator, "__protocol_attrs__") \
            else ("configure_sine", "set_frequency", "set_amplitude", "configure_pulse_burst",
                  "output_on", "output_off", "reference_locked", "safe_state", "close"):
        assert hasattr(Agilent33220A, name) or name in ("identity", "resource"), name
    t.assert_done()


def test_open_refuses_other_instrument_without_sending_anything_else():
    t = ScriptedTransport([("*IDN?", "Keysight,34461A,X,1")])
    with pytest.raises(Exception, match="not an Agilent 33220A"):
        Agilent33220A(t, "FAKE::INSTR")
    assert t.sent == ["*IDN?"] and t.closed


def test_configure_sine_exact_commands():
    g, t = make([("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 80", None),
                 ("VOLT 1.5", None), ("SYST:ERR?", OK),
                 ("FREQ 82.5", None), ("SYST:ERR?", OK),
                 ("VOLT 0.25", None), ("SYST:ERR?", OK),
                 ("OUTP ON", None), ("SYST:ERR?", OK), ("OUTP?", "1")])
    g.configure_sine(80.0, 1.5)
    g.set_frequency(82.5)
    g.set_amplitude(0.25)
    g.output_on()
    assert g.output_enabled is True
    t.assert_done()


def test_configure_pulse_burst_exact_commands():
    g, t = make([("FUNC PULS", None), ("FUNC:PULS:WIDT 1E-06", None),
                 ("PULS:PER 0.0002", None), ("FUNC:PULS:TRAN 5E-09", None),
                 ("VOLT 5", None), ("VOLT:OFFS 2.5", None), ("TRIG:SOUR EXT", None),
                 ("TRIG:SLOP POS", None), ("BURS:MODE TRIG", None),
                 ("BURS:NCYC 2000", None), ("BURS:STAT ON", None), ("SYST:ERR?", OK)])
    g.configure_pulse_burst(prf_hz=5000.0, n_pulses=2000, width_s=1e-6, high_v=5.0)
    t.assert_done()


def test_amplitude_offset_order_keeps_intermediate_states_valid():
    # from 8 Vpp/0 V to 2 Vpp/+3.5 V into 50 ohm: offset first would give 3.5+4 > 5 V,
    # so the amplitude goes first
    g, t = make([("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 100", None),
                 ("VOLT 8", None), ("SYST:ERR?", OK),
                 ("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 100", None),
                 ("VOLT 2", None), ("VOLT:OFFS 3.5", None), ("SYST:ERR?", OK),
                 ("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 100", None),
                 ("VOLT:OFFS -1", None), ("VOLT 8", None), ("SYST:ERR?", OK)])
    g.configure_sine(100, 8.0)
    g.configure_sine(100, 2.0, 3.5)
    g.configure_sine(100, 8.0, -1.0)  # 3.5 + 4 > 5: offset must move first
    t.assert_done()


def test_high_z_load_doubles_the_limits():
    # at high Z the instrument shows *RST's 0.1 Vpp as 0.2 Vpp: the levels are not taken
    # as known, and the first configuration sends the offset and the amplitude
    g, t = make([("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 10", None),
                 ("VOLT:OFFS 0", None), ("VOLT 16", None), ("SYST:ERR?", OK)], load=math.inf)
    g.configure_sine(10.0, 16.0)  # > 10 Vpp: only valid into high-Z
    t.assert_done()
    g50, t50 = make([])
    with pytest.raises(LimitError, match="for a 50 ohm load"):
        g50.configure_sine(10.0, 16.0)
    assert t50.script == []  # nothing sent


def test_instrument_error_raises_with_its_text_and_output_goes_off():
    g, t = make([("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 80", None),
                 ("VOLT 1", None), ("SYST:ERR?", '-222,"Data out of range"'),
                 ("SYST:ERR?", '+221,"Settings conflict"'), ("SYST:ERR?", OK),
                 ("OUTP OFF", None)])
    with pytest.raises(InstrumentError, match=r'-222,"Data out of range"; \+221'):
        g.configure_sine(80, 1.0)
    t.assert_done()


def test_timeout_is_clear_and_output_goes_off():
    timeout = InstrumentTimeoutError("FAKE::INSTR: no answer to 'SYST:ERR?' within 5 s")
    g, t = make([("FREQ 12", None), ("SYST:ERR?", timeout), ("OUTP OFF", None)])
    with pytest.raises(InstrumentTimeoutError, match="no answer"):
        g.set_frequency(12.0)
    t.assert_done()


def test_keyboard_interrupt_mid_block_turns_output_off():
    g, t = make([("FREQ 12", KeyboardInterrupt()), ("OUTP OFF", None)])
    with pytest.raises(KeyboardInterrupt):
        g.set_frequency(12.0)
    t.assert_done()


def test_context_manager_close_turns_output_off_once_and_never_raises():
    g, t = make([("OUTP OFF", ConnectionResetError("link down"))])
    with g:
        pass
    assert t.closed and any("link down" in m for m in g.safe_state_errors)
    g.close()  # idempotent, nothing more sent
    with pytest.raises(Exception, match="closed"):
        g.output_on()


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda g: g.configure_sine(25e6, 1.0), "sine range"),
        (lambda g: g.configure_sine(100, 0.005), "outside"),
        (lambda g: g.configure_sine(100, 4.0, 3.5), "exceeds 5 V"),
        (lambda g: g.configure_sine(float("nan"), 1.0), "frequency"),
        (lambda g: g.configure_pulse_burst(5000, 2000, 10e-9, 5.0), "below the minimum"),
        (lambda g: g.configure_pulse_burst(5000, 2000, 199.99e-6, 5.0), "period -"),
        (lambda g: g.configure_pulse_burst(5000, 2000, 50e-9, 5.0, edge_s=40e-9), "0.625"),
        (lambda g: g.configure_pulse_burst(5000, 60000, 1e-6, 5.0), "n_pulses"),
        (lambda g: g.configure_pulse_burst(6e6, 10, 20e-9, 5.0), "pulse range"),
        (lambda g: g.configure_pulse_burst(5000, 10, 1e-6, 0.0, 1.0), "high_v"),
    ],
)
def test_limits_checked_before_sending(call, match):
    g, t = make([])
    with pytest.raises(LimitError, match=match):
        call(g)
    assert t.sent[-1] == "SYST:ERR?"  # nothing after the open sequence


def test_bench_drive_limit_enforced_in_driver():
    g, t = make([("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 50", None),
                 ("VOLT 2", None), ("SYST:ERR?", OK)], max_vpp=2.0)
    g.configure_sine(50.0, 2.0)
    with pytest.raises(LimitError, match="bench limit"):
        g.set_amplitude(2.1)
    with pytest.raises(LimitError, match="bench limit"):
        g.configure_sine(50.0, 1.0, offset_v=0.6)
    t.assert_done()


def test_pulse_rules_pure():
    assert ag.min_pulse_width_s(1e-3) == 20e-9
    assert ag.min_pulse_width_s(50.0) == 200e-9
    assert ag.min_pulse_width_s(500.0) == 2e-6
    assert ag.min_pulse_width_s(1500.0) == 20e-6
    ag.check_pulse(200e-6, 1e-6, 100e-9)
    with pytest.raises(LimitError):
        ag.check_pulse(100e-9, 20e-9, 5e-9)
    assert ag.load_factor(50.0) == 1.0 and ag.load_factor(math.inf) == 2.0
    assert ag.amplitude_limits_vpp(math.inf) == pytest.approx((0.02, 20.0))


def test_reference_lock_reporting():
    g, t = make([("PHAS:UNL:ERR:STAT?", "1"), ("SYST:ERR?", OK),
                 ("PHAS:UNL:ERR:STAT?", "1"),
                 ("SYST:ERR?", '+580,"Reference phase-locked loop is unlocked"'),
                 ("SYST:ERR?", OK)])
    assert g.reference_locked() is True
    assert g.reference_locked() is False
    t.assert_done()
    g2, _ = make([], option001=False)
    assert g2.has_option_001 is False and g2.reference_locked() is None


def test_unlock_during_configuration_raises_reference_error():
    g, t = make([("FREQ 20", None),
                 ("SYST:ERR?", '+580,"Reference phase-locked loop is unlocked"'),
                 ("SYST:ERR?", OK), ("OUTP OFF", None)])
    with pytest.raises(ReferenceUnlockedError):
        g.set_frequency(20.0)


def test_command_table_is_declared_and_cited():
    table = Agilent33220A.command_table()
    gets = {c.get_cmd for c in table}
    for cmd in ["FUNC?", "FREQ?", "VOLT?", "VOLT:OFFS?", "VOLT:UNIT?", "OUTP?", "OUTP:LOAD?",
                "OUTP:SYNC?", "PULS:PER?", "FUNC:PULS:WIDT?", "FUNC:PULS:TRAN?",
                "BURS:STAT?", "BURS:MODE?", "BURS:NCYC?", "BURS:INT:PER?", "BURS:PHAS?",
                "TRIG:SOUR?", "TRIG:SLOP?", "PHAS?", "PHAS:UNL:ERR:STAT?"]:
        assert cmd in gets
    assert all(c.spec for c in table)


# ---------------------------------------------------------------- through pyvisa-sim
def sim_gen(resource=RES1, **kw):
    return Agilent33220A.open(resource, visa_library=SIM, timeout_s=0.2, **kw)


def test_sim_open_configure_and_read_back():
    with sim_gen(load_ohm="inf") as g:
        assert "33220A" in g.identity and g.has_option_001
        g.configure_sine(152.5, 1.25, 0.1)
        assert g.frequency_hz == 152.5
        assert g.amplitude == 1.25 and g.offset_v == pytest.approx(0.1)
        assert math.isinf(g.output_load)
        assert g.function == "sine"
        g.output_on()
        assert g.output_enabled
        g.configure_pulse_burst(5000, 2000, 1e-6, 5.0)
        assert g.burst_cycles == 2000 and g.burst_enabled
        assert g.trigger_source == "external" and g.pulse_period_s == pytest.approx(2e-4)
        assert g.reference_locked() is True
    # closed: the output off, and the instrument asked whether it is
    assert [c[1] for c in g.command_log[-3:]] == ["OUTP OFF", "OUTP?", "SYST:ERR?"]


def test_sim_two_generators_identify_by_their_own_serial_and_keep_their_own_state():
    # each *IDN? ends up in the session's /bench: the drive must not claim the trigger's serial
    res2 = RES1.replace("MY44000001", "MY44000002")
    with sim_gen() as g1, sim_gen(res2) as g2:
        assert "MY44000001" in g1.identity and "MY44000002" in g2.identity
        g1.configure_sine(100.0, 1.0)
        g2.configure_sine(250.0, 0.5)
        assert g1.frequency_hz == 100.0 and g2.frequency_hz == 250.0
        g2.check_errors()


def test_sim_every_declared_query_answers_and_parses():
    with sim_gen() as g:
        for control in Agilent33220A.command_table():
            control.__get__(g)  # raises on a missing/unparseable answer
        g.check_errors()


def test_sim_error_queue_reaches_the_driver():
    with sim_gen() as g:
        g.write("FREQ 3E7")  # bypasses the driver's checks on purpose
        with pytest.raises(InstrumentError, match="Command error"):
            g.check_errors()
        g.check_errors()  # queue drained


@pytest.mark.filterwarnings("ignore:read string doesn't end with termination")
def test_sim_timeout_and_lost_connection_are_clear():
    with sim_gen() as g:
        with pytest.raises(InstrumentTimeoutError, match="within 0.2 s"):
            g.ask("NOSUCH?")
        g.transport._res.close()  # the connection goes away under the driver
        with pytest.raises(InstrumentConnectionError):
            g.set_frequency(10.0)
    # pyvisa-sim "opens" unknown resources; what matters is a clear refusal
    with pytest.raises(DriverError, match="NOPE"):
        Agilent33220A.open("USB0::1::2::NOPE::INSTR", visa_library=SIM, timeout_s=0.1)


class _KeepOpen(VisaTransport):
    """A VISA transport whose close() keeps the session, so the test can look after."""

    def close(self):
        self.closed_by_driver = True


class _NullDigitizer:
    identity = resource = "none"

    def abort(self):
        pass

    def close(self):
        pass


@pytest.mark.parametrize("failure", [RuntimeError("tracking failed"), KeyboardInterrupt()])
def test_exception_mid_sweep_leaves_both_generators_off(failure):
    t1 = _KeepOpen(RES1, visa_library=SIM, timeout_s=0.5)
    t2 = _KeepOpen(RES2, visa_library=SIM, timeout_s=0.5)
    trig = Agilent33220A(t1, RES1)
    drive = Agilent33220A(t2, RES2, load_ohm=math.inf, max_vpp=2.0)
    bench = Bench(trigger=trig, drive=drive, digitizer=_NullDigitizer(), pulsers=[],
                  config=BenchConfig.default(), simulated=False)
    steps = []
    with pytest.raises(type(failure)):
        with bench:
            trig.configure_pulse_burst(5000, 2000, 1e-6, 5.0)
            drive.configure_sine(5.0, 1.0)
            trig.output_on()
            drive.output_on()
            for f in (5.0, 7.5, 10.0, 12.5):
                drive.set_frequency(f)
                steps.append(f)
                assert t1.query("OUTP?") in ("1", "ON") and t2.query("OUTP?") in ("1", "ON")
                if f == 10.0:
                    raise failure
    assert steps == [5.0, 7.5, 10.0]
    # the simulated instruments themselves say the outputs are off
    assert t1.query("OUTP?") in ("0", "OFF")
    assert t2.query("OUTP?") in ("0", "OFF")
    assert t1.closed_by_driver and t2.closed_by_driver
    for g in (trig, drive):
        assert [c[1] for c in g.command_log[-3:]] == ["OUTP OFF", "OUTP?",
                                                    "SYST:ERR?"]
        assert not g.safe_state_errors  # each confirmed off
    VisaTransport.close(t1)
    VisaTransport.close(t2)


def test_set_frequency_in_pulse_mode_keeps_the_pulse_rules():
    g, t = make([("FUNC PULS", None), ("FUNC:PULS:WIDT 1E-05", None),
                 ("PULS:PER 0.0002", None), ("FUNC:PULS:TRAN 5E-09", None),
                 ("VOLT 5", None), ("VOLT:OFFS 2.5", None), ("TRIG:SOUR EXT", None),
                 ("TRIG:SLOP POS", None), ("BURS:MODE TRIG", None),
                 ("BURS:NCYC 10", None), ("BURS:STAT ON", None), ("SYST:ERR?", OK)])
    g.configure_pulse_burst(5000, 10, 10e-6, 5.0)
    with pytest.raises(LimitError, match="pulse width"):
        g.set_frequency(100e3)  # period 10 us: a 10 us pulse no longer fits
    t.assert_done()


@settings(max_examples=60, deadline=None)
@given(old_amp=st.floats(0.01, 10.0), old_frac=st.floats(-1, 1),
       new_amp=st.floats(0.01, 10.0), new_frac=st.floats(-1, 1))
def test_amplitude_offset_ordering_never_passes_an_invalid_state(old_amp, old_frac, new_amp,
                                                                 new_frac):
    """Whatever the old and new (valid) settings, every intermediate state the command
    order produces respects |offset| + Vpp/2 <= 5 V (50 ohm)."""
    old_off = old_frac * (5.0 - old_amp / 2)
    new_off = new_frac * (5.0 - new_amp / 2)
    g, _ = make([])
    g._state.update(amplitude_vpp=old_amp, offset_v=old_off)
    amp, off = old_amp, old_off
    for cmd in g._amp_offset_commands(new_amp, new_off):
        head, value = cmd.split(" ")
        if head == "VOLT":
            amp = float(value)
        else:
            off = float(value)
        assert abs(off) + amp / 2 <= 5.0 + 1e-9, (cmd, amp, off)
    assert amp == pytest.approx(new_amp) and off == pytest.approx(new_off)


def test_interrupted_query_gets_a_device_clear_before_output_off():
    g, t = make([("FREQ 12", None), ("SYST:ERR?", KeyboardInterrupt()), ("OUTP OFF", None),
                 ("OUTP?", "0"), ("SYST:ERR?", OK)])
    with pytest.raises(KeyboardInterrupt):
        g.set_frequency(12.0)
    assert t.sent[-5:] == ["SYST:ERR?", "<clear>", "OUTP OFF", "OUTP?", "SYST:ERR?"]
    t.assert_done()


def test_sim_device_clear_is_harmless():
    with sim_gen() as g:
        g.query_interrupted = True
        g.safe_state()
        assert [c[1] for c in g.command_log[-4:]] == ["<device clear>", "OUTP OFF", "OUTP?",
                                                    "SYST:ERR?"]
        assert g.output_enabled is False and not g.safe_state_errors


def test_missing_visa_library_is_a_clear_connection_error(tmp_path):
    with pytest.raises(InstrumentConnectionError, match="cannot"):
        Agilent33220A.open(RES1, visa_library=f"{tmp_path / 'missing.yaml'}@sim")


def test_levels_are_sent_again_after_a_failed_block():
    # helper review, session 34: VOLT 4 went out, SYST:ERR? timed out (output off), and the
    # cached 1 Vpp made a retry at 1 Vpp skip VOLT: the next OUTP ON would drive at 4 Vpp
    timeout = InstrumentTimeoutError("FAKE::INSTR: no answer to 'SYST:ERR?' within 5 s")
    g, t = make([("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 100", None),
                 ("VOLT 1", None), ("SYST:ERR?", OK),
                 ("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 100", None),
                 ("VOLT 4", None), ("SYST:ERR?", timeout), ("OUTP OFF", None), ("OUTP?", "0"),
                 # the queue drained once the output is off: VOLT 4's error is not blamed
                 # on the next block
                 ("SYST:ERR?", '-222,"Data out of range"'), ("SYST:ERR?", OK),
                 ("FUNC SIN", None), ("BURS:STAT OFF", None), ("FREQ 100", None),
                 ("VOLT:OFFS 0", None), ("VOLT 1", None), ("SYST:ERR?", OK)])
    g.configure_sine(100, 1.0)
    with pytest.raises(InstrumentTimeoutError):
        g.configure_sine(100, 4.0)
    with pytest.raises(DriverError, match="configure the waveform again"):
        g.set_amplitude(0.5)  # against an offset nobody knows now: refused, nothing sent
    g.configure_sine(100, 1.0)
    t.assert_done()


def test_safe_state_asks_whether_the_output_is_off():
    g, t = make([("OUTP OFF", None), ("OUTP?", "1")])
    g.safe_state()
    t.assert_done()
    assert any("OUTP OFF not confirmed" in m and "'1'" in m for m in g.safe_state_errors)
    g2, t2 = make([("OUTP OFF", None), ("OUTP?", "0"), ("SYST:ERR?", OK)])
    g2.safe_state()
    t2.assert_done()
    assert g2.safe_state_errors == []


class _HeldQuery(ScriptedTransport):
    """Holds the answer to ``held`` (once) until ``release`` is set, as a slow instrument
    would, so that another thread can try to talk to the instrument meanwhile."""

    def __init__(self, script, held):
        super().__init__(script)
        self.held, self.entered, self.release = held, threading.Event(), threading.Event()

    def query(self, command):
        answer = super().query(command)  # sent; its answer comes late
        if command == self.held and not self.entered.is_set():
            self.entered.set()
            self.release.wait(10.0)
        return answer


def _run_thread_query_meanwhile_safe_state(script_after_open):
    t = _HeldQuery(open_script() + script_after_open, held=None)
    g = Agilent33220A(t, "FAKE::INSTR", load_ohm=50.0)
    t.sent.clear()
    t.held = "SYST:ERR?"  # the run thread's next error check
    run_thread = threading.Thread(target=g.check_errors)
    run_thread.start()
    assert t.entered.wait(5.0)  # the run thread is between its query and the answer
    abort_thread = threading.Thread(target=g.safe_state)
    abort_thread.start()
    return g, t, run_thread, abort_thread


def test_a_safe_state_from_another_thread_waits_for_the_exchange_under_way():
    # safety review, session 34: the abort path sent a device clear and OUTP OFF between
    # the run thread's query and its answer (the clear cut the query; the answers could
    # be taken by the wrong thread)
    g, t, run_thread, abort_thread = _run_thread_query_meanwhile_safe_state(
        [("SYST:ERR?", OK), ("OUTP OFF", None), ("OUTP?", "0"), ("SYST:ERR?", OK)])
    abort_thread.join(0.2)
    assert abort_thread.is_alive() and t.sent == ["SYST:ERR?"]  # waiting its turn
    t.release.set()
    run_thread.join(5.0)
    abort_thread.join(5.0)
    t.assert_done()
    assert t.sent == ["SYST:ERR?", "OUTP OFF", "OUTP?", "SYST:ERR?"]  # no device clear needed
    assert g.safe_state_errors == []


def test_a_safe_state_does_not_wait_long_for_a_stuck_exchange(monkeypatch):
    from pelvislab.drivers import scpi

    monkeypatch.setattr(scpi, "SAFE_STATE_IO_WAIT_S", 0.05)
    g, t, run_thread, abort_thread = _run_thread_query_meanwhile_safe_state(
        [("SYST:ERR?", OK), ("OUTP OFF", None)])
    abort_thread.join(5.0)
    assert not abort_thread.is_alive()  # OUTP OFF sent while the query still hangs
    # ... and not asked back: the hung query's pending read would take OUTP?'s answer
    # (review of session 35's diff: it read "0" as its SYST:ERR? answer)
    assert t.sent == ["SYST:ERR?", "<clear>", "OUTP OFF"]
    assert len(g.safe_state_errors) == 1 and "not asked back" in g.safe_state_errors[0]
    t.release.set()
    run_thread.join(5.0)
    t.assert_done()
    g.transport.script = [("OUTP OFF", None), ("OUTP?", "0"), ("SYST:ERR?", OK)]
    g.safe_state()  # the instrument is free again: confirmed, nothing forced
    assert t.sent[-3:] == ["OUTP OFF", "OUTP?", "SYST:ERR?"] and t.sent.count("<clear>") == 1
    assert len(g.safe_state_errors) == 1


def test_a_nested_forced_safe_state_keeps_the_outer_one_forced():
    # review of session 35's diff: the inner forced call's exit cleared the outer's forced
    # mode, whose remaining commands then waited for the hung exchange
    import threading as th

    g, _t = make([])
    g._io_lock.acquire()  # held by "another thread" for the whole test
    try:
        done = []

        def outer():
            with g.safe_state_io(wait_s=0.01) as free_outer:
                with g.safe_state_io(wait_s=0.01) as free_inner:
                    assert not free_outer and not free_inner
                assert g._io_forced_by == th.get_ident()  # still forced here
            assert g._io_forced_by is None
            done.append(True)

        worker = th.Thread(target=outer)
        worker.start()
        worker.join(5.0)
        assert done
    finally:
        g._io_lock.release()


def test_ctrl_c_while_the_error_queue_is_read_after_the_safe_state_is_no_failure():
    # review of session 35's diff: the output was confirmed off, yet a KeyboardInterrupt
    # during the new drain escaped and was recorded as "drive: safe state failed"
    g, t = make([("OUTP OFF", None), ("OUTP?", "0"), ("SYST:ERR?", KeyboardInterrupt())])
    g.safe_state()
    t.assert_done()
    assert g.safe_state_errors == []


def test_an_unlocked_reference_at_open_is_reported_not_taken_for_no_option_001():
    script = open_script()[:-1] + [("SYST:ERR?", '+580,"Reference phase-locked loop is '
                                    'unlocked"'), ("SYST:ERR?", OK),
                                   ("OUTP OFF", None), ("OUTP?", "0"), ("SYST:ERR?", OK)]
    t = ScriptedTransport(script)
    with pytest.raises(ReferenceUnlockedError, match="not locked to the external 10 MHz"):
        Agilent33220A(t, "FAKE::INSTR", load_ohm=50.0)
    t.assert_done()
    assert t.closed  # and its output was put off and confirmed first


def test_bad_limits_at_construction_close_the_connection():
    t = ScriptedTransport([])
    with pytest.raises(LimitError, match="max_vpp"):
        Agilent33220A(t, "FAKE::INSTR", max_vpp=-1.0)
    assert t.closed and t.sent == []


def test_a_narrower_pulse_gets_its_shorter_edge_first():
    # edge <= 0.625 x width at every step: from 1 us / 100 ns to 100 ns / 5 ns the edge
    # must shrink before the width (helper review, session 34: edge last gave -221)
    tail = [("TRIG:SOUR EXT", None), ("TRIG:SLOP POS", None), ("BURS:MODE TRIG", None),
            ("BURS:NCYC 2000", None), ("BURS:STAT ON", None), ("SYST:ERR?", OK)]
    g, t = make([("FUNC PULS", None), ("FUNC:PULS:WIDT 1E-06", None),
                 ("PULS:PER 0.0002", None), ("FUNC:PULS:TRAN 1E-07", None),
                 ("VOLT 5", None), ("VOLT:OFFS 2.5", None), *tail,
                 ("FUNC PULS", None), ("FUNC:PULS:TRAN 5E-09", None),
                 ("FUNC:PULS:WIDT 1E-07", None), ("PULS:PER 0.0002", None), *tail])
    g.configure_pulse_burst(5000.0, 2000, 1e-6, 5.0, edge_s=100e-9)
    g.configure_pulse_burst(5000.0, 2000, 100e-9, 5.0, edge_s=5e-9)
    t.assert_done()


def test_settings_of_the_table_are_made_through_the_methods_only():
    # safety review, session 34: `gen.amplitude = 15` passed the static 20 Vpp limit and
    # was sent, past the bench's max_vpp and the load's limit, with the tracked state wrong
    g, t = make([("VOLT?", "+1.0E-01")], max_vpp=2.0)
    for name, value, method in [("amplitude", 15.0, "set_amplitude"),
                                ("output", True, "output_on"),
                                ("offset_v", 1.0, "configure_sine")]:
        with pytest.raises(LimitError, match=f"{name} is not set directly; use {method}"):
            setattr(g, name, value)
    with pytest.raises(LimitError, match="outside"):  # the static limits still come first
        g.amplitude = 25.0
    assert g.amplitude == pytest.approx(0.1)  # reading is free
    t.assert_done()  # nothing was sent for the refused settings
