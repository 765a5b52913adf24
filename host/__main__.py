"""`python -m dmdsm.host` runs the `dmdsm` command."""

import sys

from .commands.entry import run

sys.exit(run())
