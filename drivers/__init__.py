"""Instrument drivers: one class per instrument, declared command tables, safe state on close."""

# A bare import (the folder itself on sys.path) is refused: see design section 3.
if __name__ != "pelvislab.drivers":  # pragma: no cover
    raise ImportError("import pelvislab.drivers, not the bare 'drivers' folder")
