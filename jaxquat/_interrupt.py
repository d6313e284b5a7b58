"""Ctrl-C while `python -m jaxquat` loads the package.

Python imports the package, and with it jax (about a second), before `jaxquat.__main__` runs, so an
interrupt then would print a traceback through runpy. While the package loads from the command line,
SIGINT instead prints the command line's one line and ends with status 130, as `_cli.main` does
(without teardown, see `_cli._exit_now`). A handler the caller installed is left alone, and the
default one is back once the package has loaded. Importing jaxquat as a library never gets here.
"""

import os
import signal
import sys


def _interrupted(signum, frame):
    try:
        sys.stderr.write("jaxquat: interrupted\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass
    os._exit(130)


def quiet_while_loading() -> None:
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _interrupted)


def loaded() -> None:
    if signal.getsignal(signal.SIGINT) is _interrupted:
        signal.signal(signal.SIGINT, signal.default_int_handler)
