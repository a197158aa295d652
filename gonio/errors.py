"""The user-facing error boundary: known mistakes become one line, never a traceback."""

from __future__ import annotations

import sys

__all__ = ["UserError", "user_error_types"]


class UserError(Exception):
    """Something the user can fix; the message is one line saying what and how."""


# (module, class) of every exception type that means "bad input", from every layer.
_USER_ERRORS = (
    ("pydantic", "ValidationError"),
    ("acquisition.config", "ConfigError"),
    ("acquisition.kinematics", "Unreachable"),
    # A rig that cannot start (no reply, latched alert): one line, not a trace.
    ("acquisition.protocols", "DeviceFault"),
    ("acquisition.store", "RunStoreError"),
    ("calibration.reduce", "CalibrationError"),
    ("calibration.decode", "FrameError"),
    ("calibration.camera_model", "BoardSpecError"),
    ("calibration.camera_model", "CalibrationInputError"),
    ("fitting.samples", "SamplesError"),
    ("fitting.result", "FitResultError"),
    ("fitting.mcmc", "ChainFileError"),
)


def user_error_types() -> tuple[type[BaseException], ...]:
    """Exception types that mean "bad input", gathered from every layer.

    Only modules already imported are consulted: an exception can only have been raised if its
    class's module (and so its bases' modules) was imported, and importing the rest here would
    cost a failing command a second or more (OpenCV, numba) for nothing.
    """
    types: list[type[BaseException]] = [
        UserError,
        FileNotFoundError,
        IsADirectoryError,
        PermissionError,
    ]
    for module, name in _USER_ERRORS:
        mod = sys.modules.get(module)
        if mod is not None and hasattr(mod, name):
            types.append(getattr(mod, name))
    return tuple(types)
