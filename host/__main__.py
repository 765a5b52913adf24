"""`python -m dmdsm.host` runs the `dmdsm` command."""

import sys

from .commands.cli import main

sys.exit(main())
