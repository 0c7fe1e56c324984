"""The simulated bench factory: ``open_simulated_bench`` (what ``open_bench(None)`` returns).

Usage::

    from pelvislab.drivers.bench import open_bench
    with open_bench(None) as bench:           # the simulated bench, default options
        ...

    from pelvislab.sim_instruments.bench import open_simulated_bench
    from pelvislab.sim_instruments.effects import SupportResonance
    from pelvislab.sim_instruments.faults import DigitizerTimeout
    bench = open_simulated_bench(seed=3, snr_db=25, effects=[SupportResonance()],
                                 faults=[DigitizerTimeout(at_acquisition=5)])
    bench.world.place(excitation="SIAS_L_x", channels={1: "SIPS_L_x", 2: "sacrum_x"})

Options (keyword arguments, all optional; an unknown one raises TypeError):

``seed`` (0): every random draw (noise, speckle, trigger offsets, drift) derives from it.
``pacing`` ("fast"): "fast" never sleeps; "realtime" waits as long as the real bench.
``model``: a ``PelvisModel`` or a model file path (default: thesis appendix E).
``effects`` ([]): effect dataclasses of :mod:`pelvislab.sim_instruments.effects`.
``faults`` ([]): fault dataclasses of :mod:`pelvislab.sim_instruments.faults`.
``snr_db`` (30): bone-echo peak envelope over noise RMS.
``excitation`` ("SIAS_R_x") and ``excitation_direction`` (default: into the bone, minus the
landmark's outward direction: (-1, 0, 0) at SIAS_R_x); ``channels`` ({1: "sacrum_x",
2: "SIPS_R_x"}): digitizer channel -> landmark.
``acoustics``: an :class:`~pelvislab.sim_instruments.echo.Acoustics` for every channel or a
``{channel: Acoustics}``; ``bone_depth_m``: shortcut for the depth (float or per channel).
``generators`` ("pyvisa-sim"): the 33220A driver over pyvisa-sim, or "python" (same driver
over a built-in responder; no YAML parsing, faster to open).
``digitizer`` ("python"): the Python ``SimDigitizer`` (fast timeouts), or "acqiris": the
product's ``AcqirisDigitizer`` driver over a simulated D1 library (``SimD1Library``; its
timeouts take wall-clock time, like the driver's).
``pulsers`` ("panametrics"): the product's ``Panametrics5077PR`` driver over a simulated
serial port (``SimSerialPort``, answering the driver's declared command table), or
"python": the ``SimPulserReceiver`` class.
``phantom``: a ``world.Phantom`` (piezoshaker and two-body phantom of ch. 8.3) used when the
excitation point is on no bone (the validation protocols); default ``Phantom()``.
``trigger_source`` ("drive_sync"): bursts start on the drive's SYNC edge; "internal": at a
random drive phase. ``trigger_latency_s`` (0), ``trigger_jitter_s`` (0): SYNC-to-first-pulse
delay and unmeasured trigger timing noise (RMS).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from pelvislab.drivers.agilent33220a import Agilent33220A
from pelvislab.drivers.bench import SIMULATED_TRIGGER_LOAD_OHM, Bench, BenchConfig
from pelvislab.model.pelvis import PelvisModel, default_model, load_model
from pelvislab.sim_instruments.echo import Acoustics
from pelvislab.sim_instruments.faults import FaultBook
from pelvislab.sim_instruments.instruments import (
    ScpiResponder,
    SimDigitizer,
    SimPulserReceiver,
    SimTransport,
)
from pelvislab.sim_instruments.layout import DEFAULT_CHANNELS, DEFAULT_EXCITATION
from pelvislab.sim_instruments.world import SimClock, World

__all__ = ["SIM_RESOURCES", "SimulatedBench", "default_instrument_classes",
           "open_simulated_bench", "yaml_path"]

SIM_RESOURCES = {
    "trigger": "USB0::0x0957::0x0407::MY44000001::INSTR",
    "drive": "USB0::0x0957::0x0407::MY44000002::INSTR",
}
"""pyvisa-sim resources of the two 33220A (defined in agilent_33220a.yaml)."""

_OPTIONS = {"seed", "pacing", "model", "effects", "faults", "snr_db", "excitation",
            "excitation_direction", "channels", "acoustics", "bone_depth_m", "generators",
            "trigger_source", "trigger_latency_s", "trigger_jitter_s", "digitizer",
            "pulsers", "phantom"}


DEFAULT_DIGITIZER = "python"
DEFAULT_PULSERS = "panametrics"
SIM_PULSER_CHANNELS = (1, 2)
"""The simulated bench opens one pulser/receiver per digitizer channel."""


def default_instrument_classes() -> dict[str, Any]:
    """The classes :func:`open_simulated_bench` opens with its default options
    (``{"trigger", "drive", "digitizer": class, "pulsers": (class per channel)}``): what
    ``protocol check`` checks a protocol against for the simulated bench."""
    from pelvislab.drivers.panametrics5077 import Panametrics5077PR

    digitizer = {"python": SimDigitizer}[DEFAULT_DIGITIZER]
    pulser = {"panametrics": Panametrics5077PR}[DEFAULT_PULSERS]
    return {"trigger": Agilent33220A, "drive": Agilent33220A, "digitizer": digitizer,
            "pulsers": tuple(pulser for _ in SIM_PULSER_CHANNELS)}


@dataclass
class SimulatedBench(Bench):
    """A :class:`~pelvislab.drivers.bench.Bench` with its simulated ``world`` (the subject,
    the physics, the truth of every acquisition, the simulated operator ``world.place``)."""

    world: World | None = None


def yaml_path() -> Path:
    """The pyvisa-sim description of the two 33220A generators."""
    return Path(str(resources.files("pelvislab.sim_instruments") / "agilent_33220a.yaml"))


def _model(spec: Any) -> PelvisModel:
    if spec is None:
        return default_model()
    if isinstance(spec, PelvisModel):
        return spec
    return load_model(Path(spec))


def _acoustics(channels: dict[int, Any], acoustics: Any, depth: Any) -> dict[int, Acoustics]:
    out: dict[int, Acoustics] = {}
    chans = sorted(set(channels) | {1, 2})
    for ch in chans:
        if isinstance(acoustics, dict):
            a = acoustics.get(ch, Acoustics())
        elif acoustics is None:
            a = Acoustics()
        else:
            a = acoustics
        if not isinstance(a, Acoustics):
            raise TypeError(f"acoustics for channel {ch} must be an Acoustics, got {a!r}")
        if depth is not None:
            d = depth.get(ch) if isinstance(depth, dict) else depth
            if d is not None:
                from dataclasses import replace

                a = replace(a, bone_depth_m=float(d))
        out[ch] = a
    return out


def open_simulated_bench(config: BenchConfig | None = None, **sim_options: Any) -> SimulatedBench:
    """Open the simulated bench (see the module docstring for ``sim_options``).

    ``config`` supplies the calibration (N/V), the drive limit and the speeds of sound the
    tracker will assume (default :meth:`BenchConfig.default`). Returns a
    :class:`SimulatedBench` (a ``Bench`` with ``simulated=True`` and ``world``).
    """
    unknown = sorted(set(sim_options) - _OPTIONS)
    if unknown:
        raise TypeError(f"open_simulated_bench: unknown option(s) {unknown}; "
                        f"known: {sorted(_OPTIONS)}")
    cfg = config if config is not None else BenchConfig.default()
    opt = sim_options
    clock = SimClock(opt.get("pacing", "fast"))
    faults = FaultBook.of(opt.get("faults"))
    channels = dict(opt.get("channels", DEFAULT_CHANNELS))
    excitation = opt.get("excitation", DEFAULT_EXCITATION)
    direction = opt.get("excitation_direction")
    from pelvislab.sim_instruments.layout import resolve

    world = World(model=_model(opt.get("model")), config=cfg, clock=clock,
                  excitation=resolve(excitation), excitation_direction=direction,
                  channels=channels,
                  acoustics=_acoustics(channels, opt.get("acoustics"), opt.get("bone_depth_m")),
                  effects=list(opt.get("effects", ())), faults=faults,
                  seed=int(opt.get("seed", 0)), snr_db=float(opt.get("snr_db", 30.0)),
                  trigger_source=opt.get("trigger_source", "drive_sync"),
                  trigger_latency_s=float(opt.get("trigger_latency_s", 0.0)),
                  trigger_jitter_s=float(opt.get("trigger_jitter_s", 0.0)),
                  phantom=opt.get("phantom"))
    kind = opt.get("generators", "pyvisa-sim")
    if kind not in ("pyvisa-sim", "python"):
        raise ValueError(f"generators must be 'pyvisa-sim' or 'python', got {kind!r}")

    opened: list[Any] = []
    try:
        gens: dict[str, Agilent33220A] = {}
        for role, state in (("trigger", world.trigger), ("drive", world.drive)):
            inst_cfg = getattr(cfg, role)
            options = dict(inst_cfg.options) if inst_cfg is not None else {}
            resource = SIM_RESOURCES[role]
            if kind == "pyvisa-sim":
                from pelvislab.drivers.scpi import VisaTransport

                inner: Any = VisaTransport(resource, timeout_s=float(options.get("timeout_s", 5)),
                                           visa_library=f"{yaml_path()}@sim")
            else:
                inner = ScpiResponder(state, resource.split("::")[3])
            transport = SimTransport(role, inner, state, clock, faults, threading.RLock())
            # the loads and limits the protocol check uses (BenchConfig's): the lower of
            # [limits] and the section's max_vpp (a section's value replaced the
            # trigger's [limits] one here: review of session 36's diff)
            load = options.get("load_ohm", "inf" if role == "drive"
                               else SIMULATED_TRIGGER_LOAD_OHM)
            limit = cfg.generator_limit_vpp(role)
            gen = Agilent33220A(transport, resource, load_ohm=_load(load), max_vpp=limit,
                                external_reference=bool(options.get("external_reference", True)))
            gen.transport_sim = transport  # type: ignore[attr-defined]
            opened.append(gen)
            gens[role] = gen
        dig_kind = opt.get("digitizer", DEFAULT_DIGITIZER)
        digitizer: Any
        if dig_kind == "python":
            digitizer = SimDigitizer(world)
        elif dig_kind == "acqiris":
            from pelvislab.drivers.acqiris import AcqirisDigitizer
            from pelvislab.sim_instruments.acqiris_sim import SimD1Library

            digitizer = AcqirisDigitizer(SimD1Library(world), "PCI::INSTR0",
                                         external_clock_hz=cfg.reference_clock_hz)
        else:
            raise ValueError(f"digitizer must be 'python' or 'acqiris', got {dig_kind!r}")
        opened.append(digitizer)
        pul_kind = opt.get("pulsers", DEFAULT_PULSERS)
        if pul_kind not in ("panametrics", "python"):
            raise ValueError(f"pulsers must be 'panametrics' or 'python', got {pul_kind!r}")
        pulsers: list[Any] = []
        for ch in SIM_PULSER_CHANNELS:
            resource = (cfg.pulsers[ch - 1].resource if len(cfg.pulsers) >= ch
                        else f"sim://5077pr/{ch}")
            if pul_kind == "python":
                pulsers.append(SimPulserReceiver(world, ch, resource))
            else:
                from pelvislab.drivers.panametrics5077 import Panametrics5077PR
                from pelvislab.sim_instruments.panametrics_sim import SimSerialPort

                port = SimSerialPort(world, ch)
                pulsers.append(Panametrics5077PR(port, resource, channel=ch))
                port.opened = True
            opened.append(pulsers[-1])
    except BaseException:
        for inst in reversed(opened):
            try:
                inst.close()
            except Exception:  # the original error is the one to report
                pass
        raise
    return SimulatedBench(trigger=gens["trigger"], drive=gens["drive"], digitizer=digitizer,
                          pulsers=list(pulsers), config=cfg, simulated=True, world=world)


def _load(value: Any) -> float:
    if isinstance(value, str) and value.strip().lower() in ("inf", "infinity", "high-z",
                                                            "highz", "hiz"):
        return float("inf")
    return float(value)
