"""Panametrics 5077PR driver against a fake serial instrument that follows the declared
(unconfirmed) command table, and against pyserial's loop:// (an echo, i.e. an instrument
that does not answer as the table expects)."""

from __future__ import annotations

import pytest

from pelvislab.drivers import panametrics5077 as pm
from pelvislab.drivers.interfaces import (
    InstrumentConnectionError,
    InstrumentTimeoutError,
    LimitError,
)
from pelvislab.drivers.panametrics5077 import Panametrics5077PR, UnexpectedAnswerError


class FakePort:
    """A 5077PR as the table describes it: 'X v' -> 'OK', 'X?' -> v, 'ID?' -> identity."""

    def __init__(self, identity="PANAMETRICS 5077PR V1.0", ack="OK", silent=(), lie=()):
        self.identity, self.ack = identity, ack
        self.silent, self.lie = set(silent), set(lie)
        self.state = {}
        self.lines = []
        self.out = b""
        self.closed = False

    def reset_input_buffer(self):
        self.out = b""

    def write(self, data):
        assert data.endswith(b"\r")
        line = data[:-1].decode()
        self.lines.append(line)
        head = line.split(" ")[0]
        if head in self.silent:
            return len(data)
        if line == "ID?":
            ans = self.identity
        elif line.endswith("?"):
            ans = self.state.get(line[:-1], "?")
            if line[:-1] in self.lie:
                ans = "WRONG"
        else:
            key, _, val = line.partition(" ")
            self.state[key] = val
            ans = self.ack
        self.out = ans.encode() + b"\r"
        return len(data)

    def read_until(self, expected=b"\n", size=None):
        out, self.out = self.out, b""
        return out

    def close(self):
        self.closed = True


def test_configure_sends_the_declared_commands_and_verifies_each():
    port = FakePort()
    p = Panametrics5077PR(port, "FAKE", channel=1)
    assert "5077" in p.identity
    p.configure(gain_db=40, pulse_energy="200V", damping_ohm=50, high_pass_hz=1e6,
                low_pass_hz=10e6)
    assert port.lines == ["ID?", "TRIG EXT", "TRIG?", "MODE PE", "MODE?", "GAIN 40", "GAIN?",
                          "VOLT 200", "VOLT?", "DAMP 50", "DAMP?", "HPF 1MHZ", "HPF?",
                          "LPF 10MHZ", "LPF?"]
    n = len(port.lines)
    p.close()
    assert port.lines[n:] == ["VOLT 100", "VOLT?", "TRIG EXT", "TRIG?"] and port.closed
    p.close()  # idempotent


def test_values_checked_against_the_table_before_sending():
    port = FakePort()
    p = Panametrics5077PR(port, "FAKE")
    for kwargs, match in [
        (dict(gain_db=70), "gain_db"),
        (dict(gain_db=40.5), "multiple"),
        (dict(pulse_energy="1kV"), "pulse_energy"),
        (dict(damping_ohm=75), "damping_ohm"),
        (dict(low_pass_hz=5e6), "low_pass_hz"),
    ]:
        args = dict(gain_db=40, pulse_energy="low", damping_ohm=50, high_pass_hz=None,
                    low_pass_hz=None) | kwargs
        with pytest.raises(LimitError, match=match):
            p.configure(**args)
    assert port.lines == ["ID?"]


def test_wrong_ack_wrong_readback_and_silence_fail_clearly_and_go_safe():
    p = Panametrics5077PR(FakePort(ack="ACK"), "FAKE")
    with pytest.raises(UnexpectedAnswerError, match="answered 'ACK'.*expects 'OK'.*manual"):
        p.configure(40, "low", 50, None, None)
    port = FakePort(lie={"GAIN"})
    p = Panametrics5077PR(port, "FAKE")
    with pytest.raises(UnexpectedAnswerError, match="'GAIN\\?' answered 'WRONG'"):
        p.configure(40, "low", 50, None, None)
    assert port.lines[-4:] == ["VOLT 100", "VOLT?", "TRIG EXT", "TRIG?"]  # safe state
    p = Panametrics5077PR(FakePort(silent={"DAMP"}), "FAKE")
    with pytest.raises(InstrumentTimeoutError, match="no answer to 'DAMP 50'"):
        p.configure(40, "low", 50, None, None)


def test_not_a_5077_refused():
    port = FakePort(identity="TEKTRONIX AFG")
    with pytest.raises(UnexpectedAnswerError, match="expected text containing '5077'"):
        Panametrics5077PR(port, "FAKE")
    assert port.closed


def test_pyserial_loop_echo_is_not_mistaken_for_an_instrument():
    # loop:// echoes what is sent: an instrument that does not speak the table's protocol
    with pytest.raises(UnexpectedAnswerError, match="identification answered 'ID\\?'"):
        Panametrics5077PR.open("loop://", timeout_s=0.05)


def test_unopenable_port_is_a_clear_connection_error():
    with pytest.raises(InstrumentConnectionError, match="cannot open serial port"):
        Panametrics5077PR.open("/dev/does-not-exist-pelvislab", timeout_s=0.05)


def test_table_is_single_and_marked_unconfirmed():
    assert all(c.status == pm.UNCONFIRMED for c in pm.COMMANDS.values())
    assert pm.SERIAL_SETTINGS["status"] == pm.UNCONFIRMED
    assert {"trigger", "gain_db", "pulse_energy", "damping_ohm", "high_pass_hz",
            "low_pass_hz"} <= set(pm.COMMANDS)


def test_a_safe_state_from_another_thread_waits_for_the_setting_under_way():
    # safety review, session 34: an abort's exchange could flush the run thread's answer
    # (reset_input_buffer) or take it; now it waits for the setting and its read-back
    import threading

    class SlowPort(FakePort):
        def __init__(self):
            super().__init__()
            self.entered, self.release = threading.Event(), threading.Event()

        def read_until(self, expected=b"\n", size=None):
            if self.lines[-1] == "GAIN?" and not self.entered.is_set():
                self.entered.set()
                self.release.wait(10.0)
            return super().read_until(expected, size)

    port = SlowPort()
    p = Panametrics5077PR(port, "FAKE")
    run_thread = threading.Thread(target=p.configure, kwargs=dict(
        gain_db=40, pulse_energy="200V", damping_ohm=50, high_pass_hz=None,
        low_pass_hz=None))
    run_thread.start()
    assert port.entered.wait(5.0)
    abort_thread = threading.Thread(target=p.safe_state)
    abort_thread.start()
    abort_thread.join(0.2)
    assert abort_thread.is_alive() and port.lines[-1] == "GAIN?"
    port.release.set()
    abort_thread.join(5.0)
    run_thread.join(5.0)
    assert p.safe_state_errors == []
    assert "VOLT 100" in port.lines[port.lines.index("GAIN?"):]
    settings = port.lines[1:]  # after ID?: each setting whole, with its read-back
    assert len(settings) % 2 == 0
    for line, check in zip(settings[::2], settings[1::2], strict=True):
        assert check == line.split(" ")[0] + "?", port.lines


def test_a_safe_state_returns_its_own_failures():
    # the bench reports what this call could not do (another thread's safe state may
    # append to the shared safe_state_errors list meanwhile)
    port = FakePort(silent={"VOLT"})
    p = Panametrics5077PR(port, "FAKE")
    p.safe_state_errors.append("an earlier failure")
    failed = p.safe_state()
    assert len(failed) == 1 and "safe state pulse_energy failed" in failed[0]
    assert p.safe_state_errors == ["an earlier failure"] + failed
    port.silent.clear()
    assert p.safe_state() == []
