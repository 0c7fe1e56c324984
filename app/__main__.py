"""``python -m pelvislab.app`` runs the command line."""

import sys

from pelvislab.app.cli import main

sys.exit(main())
