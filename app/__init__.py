"""Command line and operator GUI: thin layers over the runner and the session API."""

import os

# The numerics work on small matrices (18 DOF, 500-sample echoes) where multi-threaded BLAS
# only adds contention on the 2-core bench PC (tracking measured up to 10x slower). Must be
# set before numpy is first imported; an explicit setting by the user wins.
for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

# A bare import (the folder itself on sys.path) is refused: see design section 3.
if __name__ != "pelvislab.app":  # pragma: no cover
    raise ImportError("import pelvislab.app, not the bare 'app' folder")
