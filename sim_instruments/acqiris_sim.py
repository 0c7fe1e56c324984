"""A simulated Acqiris D1 library (AqDrv4) behind the product's real digitizer driver.

``open_simulated_bench(digitizer="acqiris")`` opens
``pelvislab.drivers.acqiris.AcqirisDigitizer(SimD1Library(world), "PCI::INSTR0")``: the real
driver (its validation, call sequence, status checks, timeout loop, readData unpacking and
horPos handling) runs against this object, whose ``AcqrsD1_*`` functions take the same
ctypes arguments as the vendor library and answer from the simulated world.

Status codes: 0 on success; ``ACQIRIS_ERROR_ACQ_TIMEOUT`` from ``waitForEndOfAcquisition``
when the world has no end of acquisition (no triggers, injected ``DigitizerTimeout``); a
lost connection raises ``OSError`` from the call, which the driver turns into
``InstrumentConnectionError``. The driver's timeout is wall-clock: a timed-out acquisition
really takes ``timeout_s`` here (the Python ``SimDigitizer`` skips it in fast pacing).
"""

from __future__ import annotations

import ctypes
import time
from typing import Any

import numpy as np

from pelvislab.drivers.acqiris import ACQIRIS_ERROR_ACQ_TIMEOUT
from pelvislab.drivers.interfaces import InstrumentConnectionError, InstrumentTimeoutError
from pelvislab.sim_instruments.world import World

__all__ = ["SimD1Library"]

_ERROR_GENERIC = -1074116608  # 0xBFFA4000: "generic" instrument error, for bad calls


def _value(arg: Any) -> Any:
    """The Python value of a ctypes argument (scalar, byref or c_char_p)."""
    if hasattr(arg, "_obj"):
        return arg._obj.value
    return getattr(arg, "value", arg)


class SimD1Library:
    """The ``AcqrsD1_*`` functions of a simulated DP235 (one instrument)."""

    SESSION = 1
    SEGMENT_PAD = 32

    def __init__(self, world: World, resource: str = "PCI::INSTR0") -> None:
        self.world = world
        self.resource = resource
        self.calls: list[str] = []
        self._horizontal = (2e-9, 0.0)
        self._vertical: dict[int, tuple[float, float]] = {}
        self._memory = (500, 1)
        self._armed = False
        self._records: dict[int, Any] | None = None
        self._timed_out = False
        self._armed_index: int | None = None

    # -- helpers ---------------------------------------------------------------------------
    def _enter(self, name: str) -> None:
        self.calls.append(name)
        # faults count acquisitions: the one armed (until read), else the next one
        index = self._armed_index if self._armed_index is not None else self.world.acquisitions
        if self.world.faults.digitizer_lost(index):
            raise OSError(f"simulated {name}: device not responding (connection lost)")

    # -- session ---------------------------------------------------------------------------
    def AcqrsD1_InitWithOptions(self, rsrc: Any, idq: Any, reset: Any, opts: Any,
                                session: Any) -> int:
        self._enter("AcqrsD1_InitWithOptions")
        name = _value(rsrc)
        if (name.decode() if isinstance(name, bytes) else str(name)) != self.resource:
            return _ERROR_GENERIC
        session._obj.value = self.SESSION
        return 0

    def AcqrsD1_getInstrumentInfo(self, s: Any, key: Any, out: Any) -> int:
        self._enter("AcqrsD1_getInstrumentInfo")
        if _value(key) == b"TbNextSegmentPad":
            out._obj.value = self.SEGMENT_PAD
            return 0
        return _ERROR_GENERIC

    def AcqrsD1_errorMessage(self, s: Any, status: Any, buf: Any) -> int:
        code = int(_value(status))
        text = {ACQIRIS_ERROR_ACQ_TIMEOUT: b"Acquisition timeout (simulated DP235)"}.get(
            code, b"simulated DP235: invalid call or setting")
        ctypes.memmove(buf, text, len(text))
        return 0

    def AcqrsD1_close(self, s: Any) -> int:
        self.calls.append("AcqrsD1_close")
        return 0

    # -- configuration ---------------------------------------------------------------------
    def AcqrsD1_configExtClock(self, *args: Any) -> int:
        self._enter("AcqrsD1_configExtClock")
        return 0

    def AcqrsD1_configHorizontal(self, s: Any, dt: Any, delay: Any) -> int:
        self._enter("AcqrsD1_configHorizontal")
        self._horizontal = (float(_value(dt)), float(_value(delay)))
        self._vertical = {}  # the driver configures the wanted channels after this call
        return 0

    def AcqrsD1_configVertical(self, s: Any, ch: Any, fs: Any, off: Any,
                               coupling: Any, bw: Any) -> int:
        self._enter("AcqrsD1_configVertical")
        self._vertical[int(_value(ch))] = (float(_value(fs)), float(_value(off)))
        return 0

    def AcqrsD1_configMemory(self, s: Any, n: Any, m: Any) -> int:
        self._enter("AcqrsD1_configMemory")
        self._memory = (int(_value(n)), int(_value(m)))
        return 0

    def AcqrsD1_configTrigClass(self, *args: Any) -> int:
        self._enter("AcqrsD1_configTrigClass")
        return 0

    def AcqrsD1_configTrigSource(self, *args: Any) -> int:
        self._enter("AcqrsD1_configTrigSource")
        return 0

    # -- acquisition -----------------------------------------------------------------------
    def AcqrsD1_acquire(self, s: Any) -> int:
        self._armed_index = None
        self._enter("AcqrsD1_acquire")
        self._armed_index = self.world.acquisitions
        self._armed = True
        self._records = None
        self._timed_out = False
        return 0

    def AcqrsD1_waitForEndOfAcquisition(self, s: Any, ms: Any) -> int:
        self._enter("AcqrsD1_waitForEndOfAcquisition")
        if not self._armed:
            return _ERROR_GENERIC
        if self._records is not None:
            return 0
        chunk_s = int(_value(ms)) / 1e3
        if self._timed_out:
            time.sleep(chunk_s)  # the driver waits on the wall clock; so does the library
            return ACQIRIS_ERROR_ACQ_TIMEOUT
        dt, delay = self._horizontal
        n, m = self._memory
        chans = sorted(self._vertical)
        fs_v, off_v = self._vertical[chans[0]]
        try:
            self._records = self.world.acquire(chans, 1.0 / dt, n, m, delay, fs_v, off_v,
                                               timeout_s=chunk_s)
        except InstrumentTimeoutError:
            self._timed_out = True
            return ACQIRIS_ERROR_ACQ_TIMEOUT
        except InstrumentConnectionError as exc:
            raise OSError(str(exc)) from exc
        return 0

    def AcqrsD1_stopAcquisition(self, s: Any) -> int:
        self.calls.append("AcqrsD1_stopAcquisition")
        self._armed = False
        self._armed_index = None
        return 0

    def AcqrsD1_readData(self, s: Any, ch: Any, rp_ref: Any, buffer: Any,
                         desc_ref: Any, segs: Any) -> int:
        self._enter("AcqrsD1_readData")
        channel = int(_value(ch))
        if self._records is None or channel not in self._records:
            return _ERROR_GENERIC
        rec = self._records[channel]
        rp, desc = rp_ref._obj, desc_ref._obj
        n, m, stride = rp.nbrSamplesInSeg, rp.nbrSegments, rp.segmentOffset
        if (m, n) != rec.codes.shape or stride < n or rp.dataArraySize < stride * m:
            return _ERROR_GENERIC
        raw = np.frombuffer(buffer, dtype=np.int8)
        first = 0
        raw[first:first + stride * m].reshape(m, stride)[:, :n] = rec.codes
        desc.returnedSamplesPerSeg = n
        desc.returnedSegments = m
        desc.indexFirstPoint = first
        desc.sampTime = 1.0 / rec.sample_rate_hz
        desc.vGain = rec.volts_per_count
        desc.vOffset = rec.volts_offset
        np.ctypeslib.as_array(segs)["horPos"][:m] = rec.trigger_offset_s
        return 0
