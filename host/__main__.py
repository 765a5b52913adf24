"""`python -m dmdsm.host` runs the `dmdsm` command."""

import sys

from .cli import main

sys.exit(main())
