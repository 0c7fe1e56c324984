"""Acqiris DP235 digitizer (2 channels, 500 MS/s, 8 bit) through the vendor D1 library.

The vendor library (AqDrv4: ``AqDrv4.dll`` on Windows, ``libAqDrv4.so`` on Linux) is loaded
with ctypes only when :meth:`AcqirisDigitizer.open` is called; nothing is imported at module
import. The instrument is addressed by its resource name (``PCI::INSTR0``).

Sequence (segmented) acquisition, thesis ch. 8 / design section 2: every external trigger
(one per ultrasound pulse) records one segment of ``n_samples``; ``n_segments`` segments
make one record; each segment carries its own sub-sample trigger position ``horPos``.

Every call's status is checked: any non-zero status (errors, and warnings such as
"setup adapted", which would silently change a requested setting) raises
:class:`AcqirisError` with the vendor's own text from ``AcqrsD1_errorMessage``.
Function signatures and constants follow the AcqirisD1Interface.h / AcqirisDataTypes.h
declarations of the AqDrv4 distribution.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import math
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from pelvislab.drivers.interfaces import (
    DriverError,
    InstrumentConnectionError,
    InstrumentError,
    InstrumentTimeoutError,
    LimitError,
    SegmentedRecord,
)

__all__ = [
    "ACQIRIS_ERROR_ACQ_TIMEOUT",
    "AcqirisDigitizer",
    "AcqirisError",
    "AcquisitionAbortedError",
    "AqDataDescriptor",
    "AqReadParameters",
    "AqSegmentDescriptor",
    "load_library",
]

log = logging.getLogger(__name__)

ViSession = ctypes.c_uint32
ViStatus = ctypes.c_int32
ViInt32 = ctypes.c_int32
ViReal64 = ctypes.c_double

ACQIRIS_ERROR_ACQ_TIMEOUT = -1074116352  # 0xBFFA4900, AcqirisErrorCodes.h

WAIT_SLICE_MS = 200
"""One ``waitForEndOfAcquisition`` call waits at most this long (the library allows up to
10 s), so that an abort from another thread ends a wait within about this time."""

# --- constants of the D1 API (AcqirisD1Interface.h) ---------------------------------------
CLOCK_INTERNAL = 0
CLOCK_EXTERNAL_REFERENCE = 2          # external 10 MHz reference
TRIG_CLASS_EDGE = 0
TRIG_SOURCE_EXTERNAL_1 = -1           # configTrigSource channel for External 1
TRIG_PATTERN_EXTERNAL_1 = -0x80000000  # 0x80000000 as a signed ViInt32
TRIG_COUPLING = {"dc": 0, "ac": 1, "dc50": 3, "ac50": 4}
TRIG_SLOPE = {"positive": 0, "negative": 1}
VERTICAL_COUPLING = {"dc1M": 1, "ac1M": 2, "dc50": 3, "ac50": 4}
READ_INT8 = 0
READ_MODE_SEQUENCE = 1                # ReadModeSeqW

# --- DP235 (data sheet, as known to us) ------------------------------------------------------
DP235_CHANNELS = (1, 2)
DP235_MAX_SAMPLES_PER_CHANNEL = 8 * 1024 * 1024
"""Acquisition memory per channel assumed, samples (8 Mi points: the largest memory option;
the thesis, ch. 8, names the DP235 but not its memory option; unconfirmed against the
unit). The simulated DP235 and the protocol check use this one figure."""
DP235_MAX_SAMPLE_RATE_HZ = 500e6
DP235_FULL_SCALE_V = (0.05, 5.0)


class AqReadParameters(ctypes.Structure):
    """``AqReadParameters`` (AcqirisDataTypes.h)."""

    _fields_ = [
        ("dataType", ctypes.c_int32), ("readMode", ctypes.c_int32),
        ("firstSegment", ctypes.c_int32), ("nbrSegments", ctypes.c_int32),
        ("firstSampleInSeg", ctypes.c_int32), ("nbrSamplesInSeg", ctypes.c_int32),
        ("segmentOffset", ctypes.c_int32), ("dataArraySize", ctypes.c_int32),
        ("segDescArraySize", ctypes.c_int32), ("flags", ctypes.c_int32),
        ("reserved", ctypes.c_int32), ("reserved2", ctypes.c_double),
        ("reserved3", ctypes.c_double),
    ]


class AqDataDescriptor(ctypes.Structure):
    """``AqDataDescriptor``: volts = vGain * code - vOffset."""

    _fields_ = [
        ("returnedSamplesPerSeg", ctypes.c_int32), ("indexFirstPoint", ctypes.c_int32),
        ("sampTime", ctypes.c_double), ("vGain", ctypes.c_double),
        ("vOffset", ctypes.c_double), ("returnedSegments", ctypes.c_int32),
        ("nbrAvgWforms", ctypes.c_int32), ("actualTriggersInAcqLo", ctypes.c_uint32),
        ("actualTriggersInAcqHi", ctypes.c_uint32), ("actualDataSize", ctypes.c_uint32),
        ("reserved2", ctypes.c_int32), ("reserved3", ctypes.c_double),
    ]


class AqSegmentDescriptor(ctypes.Structure):
    """``AqSegmentDescriptor``: horPos (s) and the trigger time stamp."""

    _fields_ = [("horPos", ctypes.c_double), ("timeStampLo", ctypes.c_uint32),
                ("timeStampHi", ctypes.c_uint32)]


class AcquisitionAbortedError(DriverError):
    """:meth:`AcqirisDigitizer.acquire` ended by :meth:`AcqirisDigitizer.abort` from
    another thread; no record is returned."""


class AcqirisError(InstrumentError):
    """A D1 library call returned a non-zero status."""

    def __init__(self, message: str, status: int, function: str) -> None:
        super().__init__(message)
        self.status = status
        self.function = function


def load_library(path: str | None = None) -> Any:
    """Load the AqDrv4 library (ctypes). ``path`` None: the platform's default name."""
    candidates: list[str] = []
    if path:
        candidates.append(path)
    else:
        found = ctypes.util.find_library("AqDrv4")
        if found:
            candidates.append(found)
        candidates.append("AqDrv4.dll" if sys.platform == "win32" else "libAqDrv4.so")
    errors = []
    for name in candidates:
        try:
            lib = ctypes.WinDLL(name) if sys.platform == "win32" else ctypes.CDLL(name)
        except OSError as exc:
            errors.append(f"{name}: {exc}")
            continue
        _declare_prototypes(lib)
        return lib
    raise InstrumentConnectionError(
        "cannot load the Acqiris D1 library (AqDrv4); install the vendor driver or set "
        f"[digitizer] library in the bench file. Tried: {'; '.join(errors)}")


def _declare_prototypes(lib: Any) -> None:
    """argtypes/restype for the functions used (AcqirisD1Interface.h)."""
    p = ctypes.POINTER
    sig: dict[str, list[Any]] = {
        "AcqrsD1_InitWithOptions": [ctypes.c_char_p, ctypes.c_uint16, ctypes.c_uint16,
                                    ctypes.c_char_p, p(ViSession)],
        "AcqrsD1_configExtClock": [ViSession, ViInt32, ViReal64, ViInt32, ViReal64, ViReal64],
        "AcqrsD1_configHorizontal": [ViSession, ViReal64, ViReal64],
        "AcqrsD1_configVertical": [ViSession, ViInt32, ViReal64, ViReal64, ViInt32, ViInt32],
        "AcqrsD1_configMemory": [ViSession, ViInt32, ViInt32],
        "AcqrsD1_configTrigClass": [ViSession, ViInt32, ViInt32, ViInt32, ViInt32, ViReal64,
                                    ViReal64],
        "AcqrsD1_configTrigSource": [ViSession, ViInt32, ViInt32, ViInt32, ViReal64, ViReal64],
        "AcqrsD1_acquire": [ViSession],
        "AcqrsD1_waitForEndOfAcquisition": [ViSession, ViInt32],
        "AcqrsD1_stopAcquisition": [ViSession],
        "AcqrsD1_readData": [ViSession, ViInt32, p(AqReadParameters), ctypes.c_void_p,
                             p(AqDataDescriptor), ctypes.c_void_p],
        "AcqrsD1_getInstrumentInfo": [ViSession, ctypes.c_char_p, ctypes.c_void_p],
        "AcqrsD1_getInstrumentData": [ViSession, ctypes.c_char_p, p(ViInt32), p(ViInt32),
                                      p(ViInt32)],
        "AcqrsD1_errorMessage": [ViSession, ViStatus, ctypes.c_char_p],
        "AcqrsD1_close": [ViSession],
    }
    for name, argtypes in sig.items():
        fn = getattr(lib, name, None) or getattr(lib, name.replace("AcqrsD1_", "Acqrs_"), None)
        if fn is None:
            continue
        fn.argtypes = argtypes
        fn.restype = ViStatus


class AcqirisDigitizer:
    """An Acqiris DP235 in sequence mode. Implements
    :class:`pelvislab.drivers.interfaces.Digitizer`.

    ``lib`` is the loaded D1 library or any object with the same ``AcqrsD1_*`` callables
    (tests pass a fake that records the calls). Use as a context manager.
    """

    model = "Acqiris DP235"

    def __init__(self, lib: Any, resource: str, *, external_clock_hz: float | None = 10e6,
                 options: str = "", reset: bool = False, trigger_level_v: float = 1.0,
                 trigger_coupling: str = "dc", trigger_slope: str = "positive",
                 input_coupling: str = "dc50", timeout_s: float | None = None) -> None:
        if trigger_coupling not in TRIG_COUPLING:
            raise LimitError(f"trigger_coupling must be one of {sorted(TRIG_COUPLING)}")
        if trigger_slope not in TRIG_SLOPE:
            raise LimitError(f"trigger_slope must be one of {sorted(TRIG_SLOPE)}")
        if input_coupling not in VERTICAL_COUPLING:
            raise LimitError(f"input_coupling must be one of {sorted(VERTICAL_COUPLING)}")
        self.lib = lib
        self.resource = resource
        self.identity = f"{self.model} at {resource}"
        self.command_log: list[tuple[float, str]] = []
        self.trigger_level_v = float(trigger_level_v)
        self.trigger_coupling = trigger_coupling
        self.trigger_slope = trigger_slope
        self.input_coupling = input_coupling
        self.default_timeout_s = timeout_s
        self.external_clock_hz = external_clock_hz
        self._id: int | None = None
        self._config: dict[str, Any] | None = None
        self._running = False
        self._abort_requested = threading.Event()
        self.segment_pad = 32
        session = ViSession(0)
        self._call("AcqrsD1_InitWithOptions", ctypes.c_char_p(resource.encode()),
                   ctypes.c_uint16(0), ctypes.c_uint16(1 if reset else 0),
                   ctypes.c_char_p(options.encode()), ctypes.byref(session))
        self._id = int(session.value)
        try:
            self._identify(resource)
            pad = ViInt32(0)
            try:
                self._call("AcqrsD1_getInstrumentInfo", self._session(),
                           ctypes.c_char_p(b"TbNextSegmentPad"), ctypes.byref(pad))
                self.segment_pad = max(int(pad.value), 0)
            except AcqirisError as exc:
                # Older firmware may not know the key; the manual's generic pad is 32.
                log.warning("%s: TbNextSegmentPad unknown (%s); using 32", resource, exc)
                self.segment_pad = 32
            if external_clock_hz:
                # The shared 10 MHz reference of design section 2 (clockType 2).
                self._call("AcqrsD1_configExtClock", self._session(),
                           ViInt32(CLOCK_EXTERNAL_REFERENCE), ViReal64(0.0), ViInt32(0),
                           ViReal64(external_clock_hz), ViReal64(DP235_MAX_SAMPLE_RATE_HZ))
            else:
                self._call("AcqrsD1_configExtClock", self._session(),
                           ViInt32(CLOCK_INTERNAL), ViReal64(0.0), ViInt32(0),
                           ViReal64(0.0), ViReal64(0.0))
        except BaseException:
            self.close()
            raise

    def _identify(self, resource: str) -> None:
        """Model and serial number into ``identity`` (informational: a library without
        getInstrumentData, or a failing call, leaves the generic identity)."""
        name = ctypes.create_string_buffer(64)
        serial, bus, slot = ViInt32(0), ViInt32(0), ViInt32(0)
        try:
            self._call("AcqrsD1_getInstrumentData", self._session(), name,
                       ctypes.byref(serial), ctypes.byref(bus), ctypes.byref(slot))
        except (AcqirisError, InstrumentConnectionError) as exc:
            log.info("%s: no instrument data (%s)", resource, exc)
            return
        model = name.value.decode("latin-1", "replace").strip()
        self.identity = f"Acqiris {model} serial {serial.value} at {resource}"
        if "235" not in model:
            log.warning("%s is a %r, the driver was written for a DP235", resource, model)

    @classmethod
    def open(cls, resource: str, *, library: str | None = None, **kwargs: Any
             ) -> AcqirisDigitizer:
        """Load the vendor library (only now) and open ``resource`` (e.g. ``PCI::INSTR0``)."""
        return cls(load_library(library), resource, **kwargs)

    # ---- plumbing -----------------------------------------------------------------------
    def _session(self) -> ViSession:
        if self._id is None:
            raise DriverError(f"{self.model} {self.resource}: closed")
        return ViSession(self._id)

    def _call(self, name: str, *args: Any) -> None:
        """Call a D1 function; any non-zero status raises with the vendor's message."""
        self.command_log.append((time.monotonic(), name))
        # Newer AqDrv4 releases deprecate some AcqrsD1_* names in favour of Acqrs_*.
        fn = getattr(self.lib, name, None) or \
            getattr(self.lib, name.replace("AcqrsD1_", "Acqrs_"), None)
        if fn is None:
            raise InstrumentConnectionError(f"the Acqiris library has no function {name}")
        try:
            status = int(fn(*args))
        except OSError as exc:  # access violation etc. inside the vendor library
            raise InstrumentConnectionError(f"{name} failed in the vendor library: {exc}"
                                            ) from exc
        if status != 0:
            raise AcqirisError(
                f"{self.model} {self.resource}: {name} returned status "
                f"{status} (0x{status & 0xFFFFFFFF:08X}): {self._message(status)}",
                status, name)

    def _message(self, status: int) -> str:
        buf = ctypes.create_string_buffer(512)
        fn = getattr(self.lib, "AcqrsD1_errorMessage", None)
        if fn is None:
            return "(no AcqrsD1_errorMessage in the library)"
        try:
            fn(ViSession(self._id or 0), ViStatus(status), buf)
        except Exception as exc:  # the message is a courtesy; the status is what matters
            return f"(errorMessage failed: {exc})"
        return buf.value.decode("latin-1", "replace").strip() or "(empty message)"

    # ---- Digitizer interface -----------------------------------------------------------
    @staticmethod
    def check_sequence(channels: Sequence[int], sample_rate_hz: float, n_samples: int,
                       n_segments: int, delay_s: float, full_scale_v: float,
                       offset_v: float = 0.0) -> None:
        """LimitError (``setting``: the argument's name) unless :meth:`configure_sequence`
        would accept these arguments: channels in (1, 2); 0 < sample_rate_hz <= 500 MS/s;
        full scale 50 mV to 5 V (DP235); n_samples, n_segments >= 1. Nothing is called:
        what ``configure_sequence`` checks first, so that a plan can be checked before the
        card is open."""
        chans = tuple(int(c) for c in channels)
        if not chans or len(set(chans)) != len(chans) or \
                any(c not in DP235_CHANNELS for c in chans):
            raise LimitError(f"channels must be distinct values of {DP235_CHANNELS}, "
                             f"got {list(channels)}", "channels")
        fs_max = DP235_MAX_SAMPLE_RATE_HZ
        if not (math.isfinite(sample_rate_hz) and 0 < sample_rate_hz <= fs_max):
            raise LimitError(f"sample_rate_hz {sample_rate_hz!r} outside (0, 500e6]",
                             "sample_rate_hz")
        for name, v in (("n_samples", n_samples), ("n_segments", n_segments)):
            if (isinstance(v, bool) or not isinstance(v, (int, float))
                    or not math.isfinite(v) or int(v) != v or v < 1):
                raise LimitError(f"{name} must be a positive integer, got {v!r}", name)
        lo, hi = DP235_FULL_SCALE_V
        if not lo <= full_scale_v <= hi:
            raise LimitError(f"full_scale_v {full_scale_v!r} outside [{lo:g}, {hi:g}] V",
                             "full_scale_v")
        for name, v in (("delay_s", delay_s), ("offset_v", offset_v)):
            if not math.isfinite(v):
                raise LimitError(f"{name} must be finite, got {v!r}", name)

    def configure_sequence(self, channels: Sequence[int], sample_rate_hz: float,
                           n_samples: int, n_segments: int, delay_s: float,
                           full_scale_v: float, offset_v: float = 0.0) -> None:
        """Sequence mode with the external trigger (External 1, edge); see Digitizer.

        Validated first (:meth:`check_sequence`): channels in (1, 2); 0 < sample_rate_hz
        <= 500 MS/s; full scale 50 mV to 5 V (DP235); n_samples, n_segments >= 1.
        """
        self._abort_requested.clear()  # a new sequence: an earlier abort is over
        self.check_sequence(channels, sample_rate_hz, n_samples, n_segments, delay_s,
                            full_scale_v, offset_v)
        chans = tuple(int(c) for c in channels)
        self._stop_if_running()
        s = self._session()
        # a configuration that fails part way leaves the card's settings mixed: acquire
        # refuses until one succeeds, instead of reading with the previous shape
        self._config = None
        self._call("AcqrsD1_configHorizontal", s, ViReal64(1.0 / sample_rate_hz),
                   ViReal64(delay_s))
        for ch in chans:
            self._call("AcqrsD1_configVertical", s, ViInt32(ch), ViReal64(full_scale_v),
                       ViReal64(offset_v), ViInt32(VERTICAL_COUPLING[self.input_coupling]),
                       ViInt32(0))
        self._call("AcqrsD1_configMemory", s, ViInt32(int(n_samples)), ViInt32(int(n_segments)))
        self._call("AcqrsD1_configTrigClass", s, ViInt32(TRIG_CLASS_EDGE),
                   ViInt32(TRIG_PATTERN_EXTERNAL_1), ViInt32(0), ViInt32(0), ViReal64(0.0),
                   ViReal64(0.0))
        self._call("AcqrsD1_configTrigSource", s, ViInt32(TRIG_SOURCE_EXTERNAL_1),
                   ViInt32(TRIG_COUPLING[self.trigger_coupling]),
                   ViInt32(TRIG_SLOPE[self.trigger_slope]),
                   ViReal64(self.trigger_level_v * 1e3), ViReal64(0.0))  # external: mV
        self._config = dict(channels=chans, sample_rate_hz=float(sample_rate_hz),
                            n_samples=int(n_samples), n_segments=int(n_segments),
                            delay_s=float(delay_s))

    def acquire(self, timeout_s: float) -> dict[int, SegmentedRecord]:
        """Arm, wait (at most ``timeout_s``), read every configured channel.

        On timeout the acquisition is stopped and :class:`InstrumentTimeoutError` says how
        many seconds passed without the expected triggers. Any failure, and
        KeyboardInterrupt, stops the acquisition before propagating.
        """
        if self._config is None:
            raise DriverError("configure_sequence() must be called before acquire()")
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise LimitError(f"timeout_s must be > 0, got {timeout_s!r}")
        cfg = self._config
        s = self._session()
        self._raise_if_aborted()  # an abort that came before this acquisition counts too
        try:
            self._call("AcqrsD1_acquire", s)
            self._running = True
            self._wait(timeout_s)
            self._running = False
            return {ch: self._read_channel(ch, cfg) for ch in cfg["channels"]}
        except BaseException:
            self._stop()  # not an abort: a retry after a timeout may acquire again
            raise

    def _wait(self, timeout_s: float) -> None:
        # Waits in slices up to the total (the library clips one wait to 10 s), checking
        # between them for an abort from another thread: its stopAcquisition need not end
        # a wait under way, and a stopped acquisition has no record worth reading.
        deadline = time.monotonic() + timeout_s
        while True:
            remaining_ms = int(math.ceil((deadline - time.monotonic()) * 1e3))
            chunk = max(1, min(remaining_ms, WAIT_SLICE_MS))
            try:
                self._call("AcqrsD1_waitForEndOfAcquisition", self._session(), ViInt32(chunk))
                self._raise_if_aborted()
                return
            except AcqirisError as exc:
                if exc.status != ACQIRIS_ERROR_ACQ_TIMEOUT:
                    raise
                self._raise_if_aborted()
                if time.monotonic() >= deadline:
                    cfg = self._config or {}
                    raise InstrumentTimeoutError(
                        f"{self.model} {self.resource}: acquisition of "
                        f"{cfg.get('n_segments')} segments not finished within "
                        f"{timeout_s:g} s (missing external triggers? check the trigger "
                        "generator output and cabling)") from exc

    def _raise_if_aborted(self) -> None:
        if self._abort_requested.is_set():
            raise AcquisitionAbortedError(
                f"{self.model} {self.resource}: acquisition aborted")

    def _read_channel(self, channel: int, cfg: dict[str, Any]) -> SegmentedRecord:
        n_samples, n_segments = cfg["n_samples"], cfg["n_segments"]
        seg_offset = n_samples
        size = (n_samples + self.segment_pad) * (n_segments + 1)
        buffer = (ctypes.c_int8 * size)()
        segs = (AqSegmentDescriptor * n_segments)()
        rp = AqReadParameters(
            dataType=READ_INT8, readMode=READ_MODE_SEQUENCE, firstSegment=0,
            nbrSegments=n_segments, firstSampleInSeg=0, nbrSamplesInSeg=n_samples,
            segmentOffset=seg_offset, dataArraySize=size,
            segDescArraySize=ctypes.sizeof(segs), flags=0, reserved=0, reserved2=0.0,
            reserved3=0.0)
        desc = AqDataDescriptor()
        self._call("AcqrsD1_readData", self._session(), ViInt32(channel), ctypes.byref(rp),
                   buffer, ctypes.byref(desc), segs)
        if desc.returnedSegments != n_segments or desc.returnedSamplesPerSeg < n_samples:
            raise InstrumentError(
                f"{self.model} {self.resource} channel {channel}: read "
                f"{desc.returnedSegments} segments x {desc.returnedSamplesPerSeg} samples, "
                f"expected {n_segments} x {n_samples}")
        raw = np.frombuffer(buffer, dtype=np.int8)
        first = int(desc.indexFirstPoint)
        idx = first + np.arange(n_segments)[:, None] * seg_offset + np.arange(n_samples)
        if idx.max() >= raw.size:
            raise InstrumentError(f"readData indexFirstPoint {first} leaves too little data")
        codes = raw[idx].copy()
        dt = float(desc.sampTime) if desc.sampTime > 0 else 1.0 / cfg["sample_rate_hz"]
        delay = cfg["delay_s"]
        hor = np.array([segs[i].horPos for i in range(n_segments)], dtype=np.float64)
        # horPos is documented as the position of the first sample w.r.t. the trigger; a
        # value near the programmed delay includes it, one within a sample does not.
        # Keep only the sub-sample part so time = delay + k dt + offset (interfaces).
        if abs(delay) > 1.5 * dt and np.all(np.abs(hor - delay) <= 1.5 * dt):
            hor = hor - delay
        return SegmentedRecord(codes=codes, trigger_offset_s=hor, sample_rate_hz=1.0 / dt,
                               delay_s=delay, volts_per_count=float(desc.vGain),
                               volts_offset=float(desc.vOffset))

    def _stop_if_running(self) -> None:
        if self._running:
            self._stop()

    def abort(self) -> None:
        """Stop a running acquisition, also from another thread: a wait under way in
        :meth:`acquire` ends within :data:`WAIT_SLICE_MS` with
        :class:`AcquisitionAbortedError`, and so does every :meth:`acquire` until the next
        :meth:`configure_sequence`. Never raises (failures are logged)."""
        if self._id is None:
            return
        # holds until the next configure_sequence() (when acquire() cleared it on entry,
        # an abort arriving just before was lost and the wait ran to its full timeout:
        # review of session 35's diff)
        self._abort_requested.set()
        self._stop()

    def _stop(self) -> None:
        """stopAcquisition; never raises (failures are logged)."""
        try:
            self._call("AcqrsD1_stopAcquisition", self._session())
        except Exception as exc:
            log.error("%s %s: stopAcquisition failed: %s", self.model, self.resource, exc)
        self._running = False

    # the bench calls safe_state() on everything that has it
    safe_state = abort

    def close(self) -> None:
        """Abort and release the instrument. Idempotent."""
        if self._id is None:
            return
        self.abort()
        try:
            self._call("AcqrsD1_close", self._session())
        except Exception as exc:
            log.error("%s %s: close failed: %s", self.model, self.resource, exc)
        finally:
            self._id = None

    def __enter__(self) -> AcqirisDigitizer:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close()
