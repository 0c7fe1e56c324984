"""Acqiris D1 driver against a fake library object that records the call sequence."""

from __future__ import annotations

import ctypes
import subprocess
import sys
import time

import numpy as np
import pytest

from pelvislab.drivers.acqiris import (
    ACQIRIS_ERROR_ACQ_TIMEOUT,
    WAIT_SLICE_MS,
    AcqirisDigitizer,
    AcqirisError,
    AcquisitionAbortedError,
)
from pelvislab.drivers.interfaces import (
    DriverError,
    InstrumentConnectionError,
    InstrumentTimeoutError,
    LimitError,
)


def _val(a):
    if hasattr(a, "_obj"):  # ctypes.byref(...)
        return a._obj
    if isinstance(a, ctypes._SimpleCData):
        return a.value
    return a


class FakeD1:
    """Stands in for AqDrv4: records every call, fills the out-parameters."""

    SESSION = 7

    def __init__(self, fail=None, timeouts=0, pad=16, first_index=3, hor_pos=None):
        self.calls = []
        self.fail = dict(fail or {})
        self.timeouts = timeouts
        self.pad = pad
        self.first_index = first_index
        self.hor_pos = hor_pos
        self.horizontal = (None, None)
        self.vertical = {}

    def names(self):
        return [c[0] for c in self.calls if c[0] != "AcqrsD1_errorMessage"]

    def __getattr__(self, name):
        if not name.startswith("AcqrsD1_"):
            raise AttributeError(name)

        def fn(*args):
            self.calls.append((name, [_val(a) for a in args]))
            if name in self.fail:
                return self.fail[name]
            handler = getattr(self, "_" + name[len("AcqrsD1_"):], None)
            return handler(*args) if handler else 0

        return fn

    def _InitWithOptions(self, rsrc, idq, reset, opts, session):
        if rsrc.value != b"PCI::INSTR0":
            return -1074118654  # a VISA-style "resource not found"
        session._obj.value = self.SESSION
        return 0

    def _getInstrumentData(self, s, name, serial, bus, slot):
        ctypes.memmove(name, b"DP235", 5)
        serial._obj.value = 1234
        return 0

    def _getInstrumentInfo(self, s, key, out):
        out._obj.value = self.pad
        return 0

    def _errorMessage(self, s, status, buf):
        text = {ACQIRIS_ERROR_ACQ_TIMEOUT: b"Acquisition timeout"}.get(
            status.value, b"The instrument reported error %d" % status.value)
        ctypes.memmove(buf, text, len(text))
        return 0

    def _configHorizontal(self, s, dt, delay):
        self.horizontal = (dt.value, delay.value)
        return 0

    def _configVertical(self, s, ch, fs, off, coupling, bw):
        self.vertical[ch.value] = (fs.value, off.value)
        return 0

    def _waitForEndOfAcquisition(self, s, ms):
        if self.timeouts:
            self.timeouts -= 1
            return ACQIRIS_ERROR_ACQ_TIMEOUT
        return 0

    def _readData(self, s, ch, rp_ref, buffer, desc_ref, segs):
        rp, desc = rp_ref._obj, desc_ref._obj
        n, m, off = rp.nbrSamplesInSeg, rp.nbrSegments, rp.segmentOffset
        assert rp.readMode == 1 and rp.dataType == 0
        assert rp.dataArraySize >= (n + self.pad) * (m + 1)
        raw = np.frombuffer(buffer, dtype=np.int8)
        for j in range(m):
            start = self.first_index + j * off
            raw[start:start + n] = self.codes(ch.value, j, n)
        dt, delay = self.horizontal
        fs, voff = self.vertical[ch.value]
        desc.returnedSamplesPerSeg = n
        desc.returnedSegments = m
        desc.indexFirstPoint = self.first_index
        desc.sampTime = dt
        desc.vGain = fs / 256.0
        desc.vOffset = voff
        for j in range(m):
            segs[j].horPos = self.hor_pos(j, dt, delay) if self.hor_pos else -dt * j / (m + 1)
        return 0

    @staticmethod
    def codes(ch, seg, n):
        return ((np.arange(n) + 10 * seg + 50 * ch) % 200 - 100).astype(np.int8)


def open_fake(fake, **kw):
    return AcqirisDigitizer(fake, "PCI::INSTR0", **kw)


def test_open_configure_acquire_exact_call_sequence():
    fake = FakeD1()
    with open_fake(fake) as dig:
        dig.configure_sequence([1, 2], 500e6, 500, 2000, 20e-6, 1.0, 0.1)
        recs = dig.acquire(timeout_s=2.0)
    assert fake.names() == [
        "AcqrsD1_InitWithOptions", "AcqrsD1_getInstrumentData", "AcqrsD1_getInstrumentInfo",
        "AcqrsD1_configExtClock",
        "AcqrsD1_configHorizontal", "AcqrsD1_configVertical", "AcqrsD1_configVertical",
        "AcqrsD1_configMemory", "AcqrsD1_configTrigClass", "AcqrsD1_configTrigSource",
        "AcqrsD1_acquire", "AcqrsD1_waitForEndOfAcquisition", "AcqrsD1_readData",
        "AcqrsD1_readData", "AcqrsD1_stopAcquisition", "AcqrsD1_close"]
    calls = dict((n, a) for n, a in fake.calls)
    assert calls["AcqrsD1_InitWithOptions"][0] == b"PCI::INSTR0"
    assert calls["AcqrsD1_configExtClock"][1:5] == [2, 0.0, 0, 10e6]  # 10 MHz reference
    assert calls["AcqrsD1_configHorizontal"][1:] == [pytest.approx(2e-9), 20e-6]
    assert calls["AcqrsD1_configMemory"][1:] == [500, 2000]
    # edge trigger on External 1 (0x80000000), DC, positive, 1 V = 1000 mV
    assert calls["AcqrsD1_configTrigClass"][1:3] == [0, -0x80000000]
    assert calls["AcqrsD1_configTrigSource"][1:5] == [-1, 0, 0, 1000.0]
    assert [a[1:] for n, a in fake.calls if n == "AcqrsD1_configVertical"] == [
        [1, 1.0, 0.1, 3, 0], [2, 1.0, 0.1, 3, 0]]
    assert all(a[0] == FakeD1.SESSION for n, a in fake.calls[1:])
    assert dig.identity == "Acqiris DP235 serial 1234 at PCI::INSTR0"
    assert set(recs) == {1, 2}
    r = recs[2]
    assert r.codes.dtype == np.int8 and r.codes.shape == (2000, 500)
    np.testing.assert_array_equal(r.codes[5], FakeD1.codes(2, 5, 500))
    np.testing.assert_array_equal(recs[1].codes[1999], FakeD1.codes(1, 1999, 500))
    assert r.sample_rate_hz == pytest.approx(500e6)
    assert r.volts_per_count == pytest.approx(1.0 / 256) and r.volts_offset == 0.1
    assert r.delay_s == 20e-6
    np.testing.assert_allclose(r.trigger_offset_s[:3], [0, -2e-9 / 2001, -4e-9 / 2001])
    assert len(dig.command_log) == len(fake.calls) - 0


def test_horpos_including_the_delay_is_reduced_to_the_subsample_part():
    fake = FakeD1(hor_pos=lambda j, dt, delay: delay - 0.25 * dt)
    dig = open_fake(fake)
    dig.configure_sequence([1], 500e6, 64, 4, 10e-6, 0.5)
    r = dig.acquire(1.0)[1]
    np.testing.assert_allclose(r.trigger_offset_s, -0.5e-9, atol=1e-15)
    dig.close()


def test_timeout_chunks_then_raises_clear_error_and_stops():
    fake = FakeD1(timeouts=10**6)
    dig = open_fake(fake)
    dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    with pytest.raises(InstrumentTimeoutError, match="not finished within 0.05 s"):
        dig.acquire(timeout_s=0.05)
    assert fake.names()[-1] == "AcqrsD1_stopAcquisition"
    waits = [a for n, a in fake.calls if n == "AcqrsD1_waitForEndOfAcquisition"]
    assert all(1 <= a[1] <= 50 for a in waits)
    dig.close()


def test_long_timeout_is_split_into_short_waits():
    # the library allows 10 s per wait; slices of WAIT_SLICE_MS let an abort end it soon
    fake = FakeD1(timeouts=3)
    dig = open_fake(fake)
    dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    dig.acquire(timeout_s=25.0)
    waits = [a[1] for n, a in fake.calls if n == "AcqrsD1_waitForEndOfAcquisition"]
    assert waits == [WAIT_SLICE_MS] * 4
    dig.close()


def test_an_abort_from_another_thread_ends_a_wait_under_way():
    # safety review, session 34: the wait went on in chunks of up to 10 s after an abort
    import threading

    class Waiting(FakeD1):
        def __init__(self):
            super().__init__()
            self.waiting = threading.Event()

        def _waitForEndOfAcquisition(self, s, ms):
            self.waiting.set()
            time.sleep(ms.value / 1e3)  # no trigger comes: each slice times out
            return ACQIRIS_ERROR_ACQ_TIMEOUT

    fake = Waiting()
    dig = open_fake(fake)
    dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    outcome = {}

    def run():
        try:
            dig.acquire(timeout_s=60.0)
        except Exception as exc:
            outcome["error"] = exc

    run_thread = threading.Thread(target=run)
    run_thread.start()
    assert fake.waiting.wait(5.0)
    t0 = time.monotonic()
    dig.abort()
    run_thread.join(10.0)
    assert not run_thread.is_alive() and time.monotonic() - t0 < 5.0
    assert isinstance(outcome.get("error"), AcquisitionAbortedError)
    assert "AcqrsD1_readData" not in fake.names()  # no record read from a stopped card
    assert fake.names()[-1] == "AcqrsD1_stopAcquisition"
    # the next acquisition is a new one
    dig.lib = FakeD1()  # a trigger comes this time
    dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    assert dig.acquire(timeout_s=1.0)[1].codes.shape == (10, 100)
    dig.close()


def test_every_nonzero_status_raises_with_the_vendor_message():
    fake = FakeD1(fail={"AcqrsD1_configMemory": -1074115840})
    dig = open_fake(fake)
    with pytest.raises(AcqirisError, match="configMemory .*The instrument reported error"):
        dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    # after a good configuration, one that fails part way leaves the card's settings
    # mixed: no acquisition with the previous shape (helper review, session 34)
    fake.fail = {}
    dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    fake.fail = {"AcqrsD1_configMemory": -1074115840}
    with pytest.raises(AcqirisError):
        dig.configure_sequence([1], 500e6, 200, 10, 0.0, 1.0)
    with pytest.raises(DriverError, match="configure_sequence"):
        dig.acquire(1.0)
    with pytest.raises(LimitError, match="n_samples"):
        dig.configure_sequence([1], 500e6, float("nan"), 10, 0.0, 1.0)
    # a warning (positive status, e.g. setup adapted) is not silently accepted either
    fake.fail = {"AcqrsD1_configHorizontal": 0x3FFA4E00}
    with pytest.raises(AcqirisError, match="0x3FFA4E00"):
        dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    dig.close()
    with pytest.raises(AcqirisError, match="InitWithOptions"):
        AcqirisDigitizer(FakeD1(), "PCI::INSTR9")


def test_read_error_and_keyboard_interrupt_abort_the_acquisition():
    fake = FakeD1(fail={"AcqrsD1_readData": -1074116096})
    dig = open_fake(fake)
    dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    with pytest.raises(AcqirisError):
        dig.acquire(1.0)
    assert fake.names()[-1] == "AcqrsD1_stopAcquisition"

    class Interrupting(FakeD1):
        def _waitForEndOfAcquisition(self, s, ms):
            raise KeyboardInterrupt

    fake2 = Interrupting()
    dig2 = open_fake(fake2)
    dig2.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    with pytest.raises(KeyboardInterrupt):
        dig2.acquire(1.0)
    assert fake2.names()[-1] == "AcqrsD1_stopAcquisition"


@pytest.mark.parametrize("args, match", [
    (([3], 500e6, 100, 10, 0.0, 1.0), "channels"),
    (([1, 1], 500e6, 100, 10, 0.0, 1.0), "channels"),
    (([1], 1e9, 100, 10, 0.0, 1.0), "sample_rate"),
    (([1], 500e6, 0, 10, 0.0, 1.0), "n_samples"),
    (([1], 500e6, 100, 10, 0.0, 10.0), "full_scale"),
])
def test_configuration_validated_before_any_call(args, match):
    fake = FakeD1()
    dig = open_fake(fake)
    n = len(fake.calls)
    with pytest.raises(LimitError, match=match):
        dig.configure_sequence(*args)
    assert len(fake.calls) == n
    with pytest.raises(Exception, match="configure_sequence"):
        dig.acquire(1.0)


def test_library_is_loaded_lazily_and_missing_library_is_clear(tmp_path):
    code = ("import ctypes, sys\n"
            "calls = []\n"
            "ctypes.CDLL = lambda *a, **k: calls.append(a)\n"
            "import pelvislab.drivers.acqiris, pelvislab.drivers.bench\n"
            "sys.exit(1 if calls else 0)\n")
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0
    with pytest.raises(InstrumentConnectionError, match="cannot load the Acqiris D1 library"):
        AcqirisDigitizer.open("PCI::INSTR0", library=str(tmp_path / "libAqDrv4.so"))


def test_library_without_instrument_data_still_opens():
    class Old(FakeD1):
        def __getattr__(self, name):
            if name == "AcqrsD1_getInstrumentData":
                raise AttributeError(name)
            return super().__getattr__(name)

    dig = AcqirisDigitizer(Old(), "PCI::INSTR0")
    assert dig.identity == "Acqiris DP235 at PCI::INSTR0"
    dig.close()


def test_an_abort_just_before_an_acquisition_is_not_lost():
    # review of session 35's diff: acquire() cleared the abort on entry, so a STOP between
    # the runner's last check and acquire() waited out the whole timeout
    fake = FakeD1(timeouts=10**6)
    dig = open_fake(fake)
    dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    dig.abort()
    t0 = time.monotonic()
    with pytest.raises(AcquisitionAbortedError):
        dig.acquire(timeout_s=3.0)
    assert time.monotonic() - t0 < 1.0
    assert "AcqrsD1_acquire" not in fake.names()  # the card is not armed again
    # a timeout is not an abort: the next acquisition may go ahead without reconfiguring
    fake2 = FakeD1(timeouts=10**6)
    dig.lib = fake2
    dig.configure_sequence([1], 500e6, 100, 10, 0.0, 1.0)
    with pytest.raises(InstrumentTimeoutError):
        dig.acquire(timeout_s=0.05)
    fake2.timeouts = 0
    assert dig.acquire(timeout_s=1.0)[1].codes.shape == (10, 100)
    dig.close()
