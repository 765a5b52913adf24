"""The `dmdsm` console entry point: SIGTERM and Ctrl-C are handled before the slow imports
(numpy, scipy, h5py), so a signal at any moment exits cleanly with 143 or 130."""

from __future__ import annotations

import signal
import sys

from .errors import Terminated, terminate


def run(argv: list[str] | None = None) -> int:
    """Import the command line and run it; a signal during the imports is one line too."""
    try:
        signal.signal(signal.SIGTERM, terminate)
    except ValueError:  # not the main thread
        pass
    try:
        from .cli import main

        return main(argv)
    except KeyboardInterrupt as e:  # before or after a command's own handling
        terminated = isinstance(e, Terminated)
        print(f"dmdsm: {'terminated' if terminated else 'interrupted'}", file=sys.stderr)
        return 143 if terminated else 130


def console() -> None:
    """`dmdsm` as installed by pip."""
    sys.exit(run())
