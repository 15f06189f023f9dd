"""The one exception type for bad user input: the CLI turns it into one line and exit code 2."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad input named by file, key and problem; printed as `file: key: problem`."""

    def __init__(self, file: str | Path | None, key: str | None, problem: str):
        self.file = str(file) if file is not None else None
        self.key = key
        self.problem = problem
        super().__init__(self.line())

    def __reduce__(self):
        # picklable across worker processes (the default would call __init__ with one argument)
        return (type(self), (self.file, self.key, self.problem))

    def line(self) -> str:
        """The single line shown to the user."""
        parts = [p for p in (self.file, self.key) if p]
        return _one_line(": ".join([*parts, self.problem]))


def _one_line(text: str) -> str:
    """Control characters (a newline in a camera name, say) shown escaped, so the message stays one line."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
