"""``python -m snds.cli`` runs the command line."""

import sys

from snds.cli import main

sys.exit(main())
