"""Exceptions of the posecal binding: one class per posecal_status, all PosecalError."""

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

STATUS_NAMES = {
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

    status = None

    def __init__(self, status, message):
        super().__init__(message)
        self.status = status
        self.status_name = STATUS_NAMES.get(status, "POSECAL_E_UNKNOWN")
        self.message = message

    def __str__(self):
        return "%s [%s]" % (self.message, self.status_name)


class InvalidArgumentError(PosecalError, ValueError):
    """NULL/None where not allowed, malformed JSON or spec, unknown key, bad value."""


class NotFoundError(PosecalError):
    """Camera, file or frame that does not exist (also: a finite source has ended)."""


class BufferTooSmallError(PosecalError):
    """Never raised by this binding (it sizes its buffers); kept for completeness."""


class TimeoutError(PosecalError):  # noqa: A001 - posecal.TimeoutError, as in posecal.h
    """No frame within the timeout."""


class DeviceError(PosecalError):
    """The camera failed or is disconnected."""


class StateError(PosecalError):
    """The call is not allowed in the current state (e.g. result before two keyframes)."""


class FileError(PosecalError):
    """A file could not be read or written (POSECAL_E_IO)."""


class InternalError(PosecalError):
    """A bug in posecal: please report the message."""


class DegenerateError(PosecalError):
    """The data cannot determine the calibration."""


class UnsupportedError(PosecalError):
    """A valid request this build, context or camera cannot do."""


ERROR_CLASSES = {
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


def error_for(status, message):
    """The exception instance for a failed status."""
    return ERROR_CLASSES.get(status, PosecalError)(status, message)
