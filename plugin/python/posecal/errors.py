"""Exceptions of the posecal binding: one class per posecal_status, all PosecalError.

Each class also derives from the Python builtin that matches its status, so code that knows
nothing of posecal still catches it: `except TimeoutError`, `except OSError`, `except ValueError`.

    status                       class                  also a
    POSECAL_E_INVALID_ARGUMENT   InvalidArgumentError   ValueError
      (binding: wrong type)      InvalidTypeError       ValueError and TypeError
    POSECAL_E_NOT_FOUND          NotFoundError          LookupError
    POSECAL_E_BUFFER_TOO_SMALL   BufferTooSmallError    ValueError
    POSECAL_E_TIMEOUT            TimeoutError           TimeoutError (an OSError)
    POSECAL_E_DEVICE             DeviceError            OSError
    POSECAL_E_STATE              StateError             RuntimeError
    POSECAL_E_IO                 FileError              OSError
    POSECAL_E_INTERNAL           InternalError          RuntimeError
    POSECAL_E_DEGENERATE         DegenerateError        ValueError
    POSECAL_E_UNSUPPORTED        UnsupportedError       NotImplementedError

The OSError subclasses have `errno` None: the C ABI reports a status, not an errno.
"""

import builtins
from typing import Dict, Optional, Tuple, Type

# Status codes of posecal.h (frozen by the ABI).
OK = 0
E_INVALID_ARGUMENT = 1
E_NOT_FOUND = 2
E_BUFFER_TOO_SMALL = 3
E_TIMEOUT = 4
E_DEVICE = 5
E_STATE = 6
E_IO = 7
E_INTERNAL = 8
E_DEGENERATE = 9
E_UNSUPPORTED = 10

STATUS_NAMES: Dict[int, str] = {
    OK: "POSECAL_OK",
    E_INVALID_ARGUMENT: "POSECAL_E_INVALID_ARGUMENT",
    E_NOT_FOUND: "POSECAL_E_NOT_FOUND",
    E_BUFFER_TOO_SMALL: "POSECAL_E_BUFFER_TOO_SMALL",
    E_TIMEOUT: "POSECAL_E_TIMEOUT",
    E_DEVICE: "POSECAL_E_DEVICE",
    E_STATE: "POSECAL_E_STATE",
    E_IO: "POSECAL_E_IO",
    E_INTERNAL: "POSECAL_E_INTERNAL",
    E_DEGENERATE: "POSECAL_E_DEGENERATE",
    E_UNSUPPORTED: "POSECAL_E_UNSUPPORTED",
}


class PosecalError(Exception):
    """A failed posecal call: `status` (int), `status_name` and the library's `message`."""

    status: Optional[int] = None

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.status_name = STATUS_NAMES.get(status, "POSECAL_E_UNKNOWN")
        self.message = message

    def __str__(self) -> str:
        return "%s [%s]" % (self.message, self.status_name)

    def __reduce__(self) -> Tuple[type, Tuple[Optional[int], str]]:
        # Pickled with its own arguments (the builtin bases would pass only the message), so
        # an error crosses multiprocessing and concurrent.futures intact.
        return (type(self), (self.status, self.message))


class InvalidArgumentError(PosecalError, ValueError):
    """NULL/None where not allowed, malformed JSON or spec, unknown key, bad value."""


class InvalidTypeError(InvalidArgumentError, TypeError):
    """An argument of the wrong type, found by the binding before calling the library: an
    image that is not uint8 or not a buffer, a path that is not a string. Status
    POSECAL_E_INVALID_ARGUMENT, as the library would say."""


class NotFoundError(PosecalError, LookupError):
    """Camera, file, feature or frame that does not exist (also: a finite source has ended)."""


class BufferTooSmallError(PosecalError, ValueError):
    """Never raised by this binding (it sizes its buffers); kept for completeness."""


class TimeoutError(PosecalError, builtins.TimeoutError):  # noqa: A001 - as in posecal.h
    """No frame within the timeout."""


class DeviceError(PosecalError, OSError):
    """The camera failed or is disconnected."""


class StateError(PosecalError, RuntimeError):
    """The call is not allowed in the current state (e.g. result before two keyframes)."""


class FileError(PosecalError, OSError):
    """A file could not be read or written (POSECAL_E_IO)."""


class InternalError(PosecalError, RuntimeError):
    """A bug in posecal: please report the message."""


class DegenerateError(PosecalError, ValueError):
    """The data cannot determine the calibration."""


class UnsupportedError(PosecalError, NotImplementedError):
    """A valid request this build, context or camera cannot do."""


ERROR_CLASSES: Dict[int, Type[PosecalError]] = {
    E_INVALID_ARGUMENT: InvalidArgumentError,
    E_NOT_FOUND: NotFoundError,
    E_BUFFER_TOO_SMALL: BufferTooSmallError,
    E_TIMEOUT: TimeoutError,
    E_DEVICE: DeviceError,
    E_STATE: StateError,
    E_IO: FileError,
    E_INTERNAL: InternalError,
    E_DEGENERATE: DegenerateError,
    E_UNSUPPORTED: UnsupportedError,
}


def error_for(status: int, message: str) -> PosecalError:
    """The exception instance for a failed status."""
    return ERROR_CLASSES.get(status, PosecalError)(status, message)
