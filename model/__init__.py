"""Pelvis model, modal analysis, FRF synthesis, identification, EMA and gap diagnosis."""

# A bare import (the folder itself on sys.path) is refused: see design section 3.
if __name__ != "pelvislab.model":  # pragma: no cover
    raise ImportError("import pelvislab.model, not the bare 'model' folder")
