"""Command line and operator GUI: thin layers over the runner and the session API."""

# A bare import (the folder itself on sys.path) is refused: see design section 3.
if __name__ != "pelvislab.app":  # pragma: no cover
    raise ImportError("import pelvislab.app, not the bare 'app' folder")
