"""Two generators on one VISA library: closing one must not cut the other's session."""

from __future__ import annotations

from importlib import resources

from pelvislab.drivers.agilent33220a import Agilent33220A

YAML = str(resources.files("pelvislab.sim_instruments") / "agilent_33220a.yaml")
FIRST = "USB0::0x0957::0x0407::MY44000001::INSTR"
SECOND = "USB0::0x0957::0x0407::MY44000002::INSTR"


def test_closing_one_generator_leaves_the_other_usable():
    a = Agilent33220A.open(FIRST, visa_library=f"{YAML}@sim")
    b = Agilent33220A.open(SECOND, visa_library=f"{YAML}@sim")
    try:
        a.close()
        b.output_off()  # raised "Invalid session handle" when close() closed the shared RM
        assert b.output_enabled is False
    finally:
        b.close()
