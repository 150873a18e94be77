"""A command that cannot run, refused before anything runs or is written."""

from __future__ import annotations

EXIT_REFUSED = 2
"""The exit status of every refusal (a setting, a grid, a device or the data that stops a command
before it runs anything), as argparse gives a usage error; 1 stays for a sweep with a failed run."""


class Refused(SystemExit):
    """The one-block message of a refused command (``invalid config, nothing was run: ...``). It is
    a SystemExit, so code that calls the runner from Python stops as before; the command lines
    print the message and exit with ``EXIT_REFUSED``."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message
