"""The interpreter's one error type: every user mistake is reported as ``FILE:LINE: message``."""

from __future__ import annotations


class GCodeError(Exception):
    """A problem in a G-code program (or a file it reads), with where it is.

    The interpreter raises nothing else for bad input; the CLI prints ``str(err)`` and exits
    non-zero, with no traceback.
    """

    def __init__(self, message: str, file: str = "", line: int = 0) -> None:
        super().__init__(message)
        self.message = message
        self.file = file
        self.line = line

    def located(self, file: str, line: int) -> GCodeError:
        """Fill in the place if the raiser did not know it (returns self for ``raise ... from``)."""
        if not self.file:
            self.file = file
        if not self.line:
            self.line = line
        return self

    def __str__(self) -> str:
        if self.file or self.line:
            return f"{self.file or '<input>'}:{self.line}: {self.message}"
        return self.message
