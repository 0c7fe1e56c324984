"""Echo tracking, phasors, FRF estimation, the sweep runner and HDF5 session I/O (no Qt)."""

# A bare import (the folder itself on sys.path) is refused: see design section 3.
if __name__ != "pelvislab.acquisition":  # pragma: no cover
    raise ImportError("import pelvislab.acquisition, not the bare 'acquisition' folder")
