"""Protocol files (TOML) and the landmark catalogue shipped with pelvislab; data only."""

# A bare import (the folder itself on sys.path) is refused: see design section 3.
if __name__ != "pelvislab.protocols":  # pragma: no cover
    raise ImportError("import pelvislab.protocols, not the bare 'protocols' folder")
