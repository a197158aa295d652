"""The `gonio` command line. Subcommand names and options are contracts (issue #2).

The commands live in modules by what they work on (`lab`, `fit`, `studies`), registered on one
typer application (`_app`); `main` is the one place where errors meet the user: a
`plumbing.errors.UserError` (or a usage error) is one line and exit 2, never a traceback.
"""

from __future__ import annotations

import errno
import os
import sys
import warnings

import typer

from gonio.cli import fit, lab, studies, texels  # noqa: F401 - registers the commands
from gonio.cli._app import app, err

__all__ = ["app", "main"]


_ENVIRONMENT = {
    errno.EROFS: "write the output to a writable disk (see the command's --out)",
    errno.EACCES: "check the file's permissions, or write elsewhere",
    errno.EPERM: "check the file's permissions, or write elsewhere",
    errno.ENOSPC: "free some space and run the command again",
    errno.EDQUOT: "free some space within your quota and run the command again",
    # an --out that is, or sits under, a regular file
    errno.ENOTDIR: "a part of that path is a file, not a folder; choose another path (--out)",
    errno.EEXIST: "gonio does not replace it; choose another path (--out)",
}


def _say(line: str) -> None:
    """The command's last line, on the stderr the process started with: a library may have
    pointed file descriptor 2 elsewhere for a moment in another thread (calibration.decode
    collects what C decoders print), and that must not swallow the one line the user gets."""
    sys.stderr.flush()
    if _STDERR_FD is None or sys.stderr is not sys.__stderr__:  # Python-level redirection
        sys.stderr.write(line)
        return
    os.write(_STDERR_FD, line.encode("utf-8", "replace"))


def _stderr_copy() -> int | None:
    try:
        return os.dup(2)
    except OSError:  # no stderr at all (a daemon): say it where Python can
        return None


#: A copy of the stderr descriptor as it was at start (see _say).
_STDERR_FD = _stderr_copy()


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    """A warning as one line, its message's first (Python appends the library's source line)."""
    text = str(message).strip()
    return f"warning: {text.splitlines()[0] if text else category.__name__}\n"


def main() -> None:
    """Entry point: user mistakes print one line (no traceback) and exit 2."""
    warnings.filterwarnings("ignore", category=FutureWarning)
    # numpy's floating-point warnings (0/0 in a file's values, overflow) are not the user's to
    # read: what matters is said in words (a verdict, a one-line error). Other warnings print
    # as one line, without the library source line Python appends.
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    warnings.formatwarning = _one_line_warning
    from gonio.errors import user_error_types

    debug = "--debug" in sys.argv[1:] or os.environ.get("GONIO_DEBUG") == "1"
    try:
        rc = app(standalone_mode=False)
        if isinstance(rc, int) and rc:
            sys.exit(rc)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        err.print("aborted")
        sys.exit(130)
    except KeyboardInterrupt:
        err.print("interrupted")
        sys.exit(130)
    except Exception as exc:  # the one place where errors meet the user
        # Usage errors (unknown option, bad value) are click exceptions — but typer ≥ 0.16
        # vendors click, so match the class by name across both copies rather than by identity.
        if any(c.__name__ == "ClickException" for c in type(exc).__mro__):
            exc.show()  # type: ignore[attr-defined]
            sys.exit(exc.exit_code)
        if debug:
            raise
        if isinstance(exc, user_error_types()):
            msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            # Plain write, not rich: rich would wrap a long path onto a second line.
            _say(f"error: {msg}\n")
            sys.exit(2)
        if isinstance(exc, OSError) and exc.errno in _ENVIRONMENT:
            # The machine, not gonio, refused (read-only medium, permissions, full disk, a
            # file where a folder belongs): the user can fix that, so it is one line naming
            # the file, not an internal error.
            where = f"{exc.filename}: " if exc.filename else ""
            _say(f"error: {where}{exc.strerror}; {_ENVIRONMENT[exc.errno]}\n")
            sys.exit(2)
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        _say(f"internal error: {type(exc).__name__}: {first} (run with --debug for a traceback)\n")
        sys.exit(1)
