"""The user-error base class: something the user can fix (bad input, a device that cannot
start, an operator who declined). Every such error in every layer derives from `UserError`; the
command line catches this one class and prints its message as one line (exit 2), never a
traceback. The message is one line saying what is wrong and what to do."""

from __future__ import annotations

__all__ = ["UserError"]


class UserError(Exception):
    """Something the user can fix; the message is one line saying what and how."""
