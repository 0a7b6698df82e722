"""The ``sunrig`` console script's entry: light, so that it runs before anything heavy loads.

rig.cli imports much (and its commands more) before :func:`rig.cli.main` installs the stop
handlers (rig/stopping.py); a Ctrl-C in that first fraction of a second raised KeyboardInterrupt
inside an import and printed a traceback. Here it is what a Ctrl-C is once the command runs: exit
130, one line, no traceback. Import only the standard library here.
"""

from __future__ import annotations

import signal
import sys

EXIT_INTERRUPTED = 128 + int(signal.SIGINT)  # the shell's code for death by Ctrl-C


def console_main() -> int:
    """The ``sunrig`` command: :func:`rig.cli.console_main`, with a Ctrl-C before the command's
    own stop handlers are in place an exit 130 rather than a traceback."""
    try:
        import rig.cli

        # Also catches one between the import and main() installing its handlers (parsing the
        # arguments); main() itself turns every later one into its exit code.
        return rig.cli.console_main()
    except KeyboardInterrupt:
        # A second Ctrl-C (an impatient user, or GNU timeout's signal to the group) must not
        # interrupt the line below with a traceback of its own.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        print("sunrig: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
