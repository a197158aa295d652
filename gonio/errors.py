"""The user-facing error boundary: known mistakes become one line, never a traceback.

Every "you can fix this" error of every layer derives from `plumbing.errors.UserError`
(config mistakes, unreadable runs and frames, devices that cannot start, an operator who
declined...), so the command line catches one class. Besides it, only what other libraries
raise for a user's mistake: pydantic's ValidationError (a bad value built from the command
line) and the OS's missing-file / is-a-directory / permission errors.
"""

from __future__ import annotations

from pydantic import ValidationError

from plumbing.errors import UserError

__all__ = ["UserError", "user_error_types"]


def user_error_types() -> tuple[type[BaseException], ...]:
    """Exception types that mean "bad input" (see module doc)."""
    return (UserError, ValidationError, FileNotFoundError, IsADirectoryError, PermissionError)
