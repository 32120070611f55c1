"""Errors (and warnings) raised at the edges of the backend.

`InputError` is the one exception the command line turns into exit code 2 and a
one-line message: it always names the offending file (or argument) and says what
was expected.  Everything else escaping the backend is an internal error (exit 1).

`InputWarning` (issued by `warn_input`) is an input that is accepted but implausible
(an rms height of metres, a checksum that does not match); it too names the file and
says why, and the command line prints it as one line ``relief: warning: FILE: ...``.
"""
from __future__ import annotations

import warnings
from pathlib import Path


class InputError(ValueError):
    """Bad user input: a file, a key, a line or an argument that breaks a contract."""

    def __init__(self, where: str | Path | None, message: str):
        self.where = str(where) if where is not None else None
        self.message = message
        super().__init__(self.one_line())

    def one_line(self) -> str:
        if self.where:
            return f"{self.where}: {self.message}"
        return self.message


class RequestError(InputError):
    """A reconstruction or simulation request the chosen method cannot honour."""

    def __init__(self, message: str, where: str | None = "request"):
        super().__init__(where, message)


class InputWarning(UserWarning):
    """An accepted but implausible input: the message names the file and says why."""


def warn_input(where: str | Path | None, message: str) -> None:
    """Issue an `InputWarning` "<where>: <message>" (shown once per distinct message)."""
    text = f"{where}: {message}" if where else message
    warnings.warn(InputWarning(text), stacklevel=3)


def warning_line(message, category) -> str:
    """The one line a warning shows as, wherever it is shown (the CLI's stderr, a Blender report):
    ``relief: warning: MESSAGE`` (first line of the message only)."""
    text = str(message).strip().splitlines()[0] if str(message).strip() else category.__name__
    return f"relief: warning: {text}" if issubclass(category, (InputWarning, RuntimeWarning, UserWarning)) \
        else f"relief: warning: {category.__name__}: {text}"
