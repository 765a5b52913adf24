"""The `dmdsm` console entry point, the host's top layer: the commands' parser with the demo's
`dmdsm demo` added; SIGTERM and Ctrl-C are handled before the slow imports (numpy, scipy,
h5py), so a signal at any moment exits cleanly with 143 or 130."""

from __future__ import annotations

import argparse
import signal
import sys

from .commands.errors import Terminated, terminate


def build_parser() -> argparse.ArgumentParser:
    """The whole `dmdsm` parser: every command and `dmdsm demo`."""
    from .commands import cli
    from .demo import command as demo

    return cli.build_parser(extra=(demo.add_parser,))


def main(argv: list[str] | None = None) -> int:
    """Run `dmdsm` (every command and `dmdsm demo`) without run()'s signal holding."""
    from .commands import cli
    from .demo import command as demo

    return cli.main(argv, extra=(demo.add_parser,))


def run(argv: list[str] | None = None) -> int:
    """Import the command line and run it. Ctrl-C or SIGTERM during the imports is held
    until they finish, then taken as usual: an import cut in half leaves modules broken
    (a library's bare `except:` may even swallow the interrupt), and the interpreter may
    then exit by the signal instead of with 130."""
    pending: list[int] = []
    held = _hold_signals(pending)
    try:
        try:
            from .commands import cli  # noqa: F401 (the slow imports, with the signals held)
            from .demo import command  # noqa: F401
        finally:
            _release_signals(held)
        if pending:
            raise Terminated() if pending[0] == signal.SIGTERM else KeyboardInterrupt()
        return main(argv)
    except KeyboardInterrupt as e:  # before or after a command's own handling
        terminated = isinstance(e, Terminated)
        print(f"dmdsm: {'terminated' if terminated else 'interrupted'}", file=sys.stderr)
        return 143 if terminated else 130


def console() -> None:
    """`dmdsm` as installed by pip."""
    sys.exit(run())


def _hold_signals(pending: list[int]) -> dict:
    """Record SIGINT (if Python's Ctrl-C handler is in place) and SIGTERM in `pending`
    instead of raising; returns what to restore (nothing outside the main thread)."""
    def record(signum: int, frame: object) -> None:
        pending.append(signum)

    held = {}
    try:
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            held[signal.SIGINT] = signal.signal(signal.SIGINT, record)
        held[signal.SIGTERM] = signal.signal(signal.SIGTERM, record)
    except ValueError:  # not the main thread (a test calling run): leave the handlers
        pass
    return held


def _release_signals(held: dict) -> None:
    """Ctrl-C raises KeyboardInterrupt again and SIGTERM raises Terminated."""
    for signum in held:
        signal.signal(signum, terminate if signum == signal.SIGTERM else held[signum])
