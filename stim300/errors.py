"""Every error the driver raises on purpose, under one root: `except Stim300Error` catches them all.

Each class also derives from the built-in a caller would have caught before (`OSError` for a
port, `ValueError` for bytes or values the protocol does not allow, `TimeoutError` for a silent
sensor), so existing `except` sites keep working. Misuse of an in-process API (a RingBuffer
capacity or cursor out of range, a wrong array type) stays a plain ValueError / TypeError: that
is a bug in the caller, not something the sensor, the port or a user sent.
"""

from __future__ import annotations


class Stim300Error(Exception):
    """The root of every error the driver raises on purpose."""


class FormatError(Stim300Error, ValueError):
    """A value or byte sequence the STIM300 protocol does not allow (a datagram field, a format
    option, a special datagram frame, a Service Mode command)."""


class PortError(Stim300Error, OSError):
    """A serial port could not be opened or used; the message is one line naming the port."""


class ServiceError(Stim300Error):
    """The sensor answered a Service Mode command with an error (`code` from `Ennn`, else None)."""

    def __init__(self, command: str, code: int | None, text: str):
        label = f"E{code:03d} " if code is not None else "unexpected reply: "
        super().__init__(f"service command {command!r}: {label}{text}")
        self.command = command
        self.code = code
        self.text = text


class ServiceTimeout(ServiceError, TimeoutError):
    """No Service Mode prompt or answer in time: the unit is not listening, or the line is dead.
    `command` is the one whose answer was awaited (SERVICEMODE for the first prompt)."""

    def __init__(self, command: str, message: str):
        Stim300Error.__init__(self, message)
        self.command = command
        self.code = None
        self.text = message


class UsageError(Stim300Error):
    """A problem with what the user gave a command: reported as one line, exit status 2."""


def os_reason(exc: OSError) -> str:
    """What an OSError says, as the tail of a one-line refusal: the system's words in lower case
    ("no such file or directory"), else the exception's own text on one line."""
    return (exc.strerror or " ".join(str(exc).split()) or type(exc).__name__).lower()
