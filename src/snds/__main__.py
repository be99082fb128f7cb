"""``python -m snds`` runs the command line."""

import sys

from snds.cli import main

sys.exit(main())
