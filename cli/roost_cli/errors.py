"""The one exception the CLI shows to people instead of a traceback.

Every message says what went wrong *and what to do next*. ``roost``'s app
(:class:`roost_cli.main.RoostApp`) prints it in red on stderr and exits with status 1;
anything else that escapes is a bug and keeps its traceback.
"""

from __future__ import annotations


class CliError(Exception):
    """A failure the user can act on; ``str(error)`` is the whole message."""
