"""`python -m dmdsm.host` runs the `dmdsm` command."""

import sys

from .entry import run

sys.exit(run())
