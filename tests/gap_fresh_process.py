"""The gap diagnosis of a file run in a fresh interpreter, as the command line runs it.

On fragile sets the path to a verdict turns on rounding, and rounding on the BLAS's
threading: the command line sets single-threaded BLAS before numpy loads
(``pelvislab.app``), while the test process has numpy loaded long before and may hold
threads left by other tests (then the fits run serially, see
:mod:`pelvislab.model.parallel`). Judge-like set 9753_019 gave a held-out gap of 0.104
in one and 0.11 in the other, and a different verdict path.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

_CODE = """\
import json, sys
from pelvislab.acquisition.frfset import read_frf
from pelvislab.model import gap
from pelvislab.model.pelvis import default_model
frf = read_frf(sys.argv[1])
data = gap.prepare_data(frf.frequency_hz, frf.H, frf.H_std, frf.outputs, frf.inputs)
options = json.loads(sys.argv[2])
if options.get("effects") is not None:
    options["effects"] = tuple(options["effects"])
print(json.dumps(gap.diagnose(data, default_model(), gap.GapOptions(**options)).report))
"""


def diagnose_in_fresh_process(path: str | Path, **options: object) -> dict:
    """``model.gap.diagnose(...).report`` of the /frf of ``path`` with
    ``GapOptions(**options)`` (JSON-able values; ``effects`` a list or tuple), computed in
    a new interpreter with single-threaded BLAS."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", _CODE, str(path), json.dumps(options)],
                         env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])
