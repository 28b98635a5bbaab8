"""Exceptions: one class per ``hz_status``, all subclasses of :class:`HarmonizerError`."""

from __future__ import annotations

import enum


class Status(enum.IntEnum):
    """The library's ``hz_status`` codes (values never change)."""

    OK = 0
    INVALID_ARGUMENT = 1
    INVALID_OPERATION = 2
    OUT_OF_MEMORY = 3
    MODEL = 4
    RUNTIME_MISSING = 5
    CANCELLED = 6
    UNKNOWN = 7
    IO = 8
    NOT_SUPPORTED = 9


class HarmonizerError(Exception):
    """Base class of every harmonizer error.

    ``status`` is the library's status code (``None`` when the error was raised
    before the library was called, for example when it cannot be found);
    ``message`` is the library's message, which names the function, the input
    and the value seen.
    """

    status: Status | None
    message: str

    def __init__(self, message: str, status: Status | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.status = status


class InvalidArgumentError(HarmonizerError, ValueError):
    """A bad argument or input (size, stride, channel count, parameter name or value)."""


class InvalidOperationError(HarmonizerError, RuntimeError):
    """The call is not allowed now (closed object, uncommitted parameters, no frame yet)."""


class OutOfMemoryError(HarmonizerError, MemoryError):
    """A buffer could not be allocated within the memory limit."""


class ModelError(HarmonizerError):
    """The model or its manifest is missing, malformed or incompatible."""


class RuntimeMissingError(HarmonizerError):
    """The ONNX Runtime shared library could not be found or loaded."""


class CancelledError(HarmonizerError):
    """The progress callback returned False; the session's state is unchanged."""


class IoError(HarmonizerError, OSError):
    """Reading or writing a file failed."""


class NotSupportedError(HarmonizerError):
    """Something this build does not support (including a library of another major version)."""


class UnknownError(HarmonizerError):
    """An internal error of the library (a bug: please report the message)."""


class LibraryNotFoundError(HarmonizerError, OSError):
    """``libharmonizer`` was not found or could not be loaded."""


_BY_STATUS: dict[int, type[HarmonizerError]] = {
    Status.INVALID_ARGUMENT: InvalidArgumentError,
    Status.INVALID_OPERATION: InvalidOperationError,
    Status.OUT_OF_MEMORY: OutOfMemoryError,
    Status.MODEL: ModelError,
    Status.RUNTIME_MISSING: RuntimeMissingError,
    Status.CANCELLED: CancelledError,
    Status.UNKNOWN: UnknownError,
    Status.IO: IoError,
    Status.NOT_SUPPORTED: NotSupportedError,
}


def error_for(status: int, message: str) -> HarmonizerError:
    """The exception for a status code and the library's message."""
    try:
        st: Status | None = Status(status)
    except ValueError:
        st = None
    cls = _BY_STATUS.get(status, UnknownError)
    if st is None:
        message = f"{message} (unknown status {status})"
        st = Status.UNKNOWN
    return cls(message, st)
