"""The simulated bench: virtual instruments and the physics behind them."""

# A bare import (the folder itself on sys.path) is refused: see design section 3.
if __name__ != "pelvislab.sim_instruments":  # pragma: no cover
    raise ImportError("import pelvislab.sim_instruments, not the bare 'sim_instruments' folder")
