"""The user-facing error boundary: known mistakes become one line, never a traceback."""

from __future__ import annotations

__all__ = ["UserError", "user_error_types"]


class UserError(Exception):
    """Something the user can fix; the message is one line saying what and how."""


def user_error_types() -> tuple[type[BaseException], ...]:
    """Exception types that mean "bad input", gathered from every layer."""
    from pydantic import ValidationError

    from acquisition.config import ConfigError
    from acquisition.kinematics import Unreachable
    from acquisition.protocols import DeviceFault
    from acquisition.store import RunStoreError
    from calibration.reduce import CalibrationError
    from fitting.samples import SamplesError

    types: list[type[BaseException]] = [
        UserError,
        ConfigError,
        DeviceFault,  # a rig that cannot start (no reply, latched alert): one line, not a trace
        Unreachable,
        RunStoreError,
        CalibrationError,
        SamplesError,
        ValidationError,
        FileNotFoundError,
        IsADirectoryError,
        PermissionError,
    ]
    from calibration.camera_model import BoardSpecError, CalibrationInputError
    from calibration.decode import FrameError

    types += [FrameError, BoardSpecError, CalibrationInputError]
    return tuple(types)
