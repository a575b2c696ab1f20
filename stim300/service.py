"""Service Mode (protocol doc §10): enter it, run one-line commands, leave it back to datagrams.

These work on an open `serial.Serial` that nothing else is reading: stop the `PortReader`
first. A refused command raises `ServiceError`; silence past the timeout `ServiceTimeout`.
`service_mode` wraps a session so the unit always goes back to Normal Mode; `save_to_flash`
and `change_bit_rate` are the two exchanges that do not end with a plain prompt.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager

import serial

from .errors import FormatError, ServiceError, ServiceTimeout, Stim300Error
from .serialread import read_available

PROMPT = b"\r>"
SERVICEMODE_REQUEST = b"SERVICEMODE\r"
ENTER_SETTLE_S = 0.05  # silence after CR '>' that proves it was the prompt, not datagram bytes
_ERROR_REPLY = re.compile(r"E(\d{3})\s*(.*)", re.S)
_EXIT_LINE = re.compile(rb"SYSTEM RETURNING TO (?:NORMAL|INIT) MODE\.?\r")
# The report: printable ASCII, the Latin-1 signs a real unit prints (0xB0 deg, 0xB1 +-) and line
# ends, from its first letter on (its first line is a name); any other byte is the datagram's
_REPORT = re.compile(rb"[A-Za-z][\t\n\r\x20-\x7e\xb0\xb1]*\Z")


def _read_until(ser: serial.Serial, done, timeout: float, what: str, command: str) -> bytearray:
    """Read until `done(buf)` is true; ServiceTimeout after `timeout` s (plus one port timeout)."""
    deadline = time.monotonic() + timeout
    buf = bytearray()
    while not done(buf):
        if time.monotonic() >= deadline:
            raise ServiceTimeout(command, f"{ser.port}: no {what} within {timeout} s; last bytes {bytes(buf[-24:])!r}")
        buf += read_available(ser)
    return buf


def _text(raw: bytes) -> str:
    """Service Mode text (Latin-1) with CR / CR LF line ends as '\\n', surrounding blank space removed."""
    return raw.decode("latin-1").replace("\r\n", "\n").replace("\r", "\n").strip()


def _reply(command: str, body: bytes) -> str:
    """The text of a reply without the command's echo; raises ServiceError on `Ennn ...`."""
    echo = command.encode("ascii") + b"\r"
    if body.startswith(echo):
        body = body[len(echo):]
    text = _text(body)
    error = _ERROR_REPLY.match(text)
    if error:
        raise ServiceError(command, int(error[1]), error[2].strip())
    return text


def enter_service_mode(ser: serial.Serial, timeout: float = 3.0) -> str:
    """Send SERVICEMODE; return the information report printed before the first prompt.

    The unit finishes the datagram in progress first, so binary bytes precede the report; the
    prompt counts only once the line stays quiet after it. The report is the text after the
    last byte no report holds (controls but TAB, LF, CR; DEL; Latin-1 bytes other than its deg
    and +- signs, 0xB0 and 0xB1), from its first letter on: the signs inside it are kept, and
    datagram bytes that happen to be digits, punctuation or those signs in front of it are not.
    Only datagram bytes that are letters right before the report cannot be told from it: read
    `i` for fields (as `stim300.configure` does), not this banner.
    """
    ser.reset_input_buffer()
    ser.write(SERVICEMODE_REQUEST)

    def prompted(buf: bytearray) -> bool:
        if not buf.endswith(PROMPT):
            return False
        time.sleep(ENTER_SETTLE_S)
        return not ser.in_waiting

    buf = _read_until(ser, prompted, timeout, "Service Mode prompt", SERVICEMODE_REQUEST.decode().strip())
    body = bytes(buf[:-len(PROMPT)])
    report = _REPORT.search(body)
    return _text(report[0]) if report else ""


def service_command(ser: serial.Serial, command: str, timeout: float = 3.0) -> str:
    """Run one Service Mode command (e.g. "i m", "m 4"); return its reply text.

    Not for commands that ask for confirmation (`s`, lower-case `x n`): they end without a prompt.
    """
    if "\r" in command or "\n" in command:
        raise FormatError(f"a Service Mode command is one line, got {command!r}")
    ser.write(command.encode("ascii") + b"\r")
    buf = _read_until(ser, lambda b: PROMPT in b, timeout, f"prompt after {command!r}", command)
    return _reply(command, bytes(buf[:buf.index(PROMPT)]))


def exit_service_mode(ser: serial.Serial, to: str = "N", timeout: float = 3.0) -> bytes:
    """Leave Service Mode at once (`x N` to Normal, `x I` to Init Mode, no confirmation).

    The unit echoes the command and prints SYSTEM RETURNING TO ... MODE (real firmware: no
    period, no prompt), then datagrams follow at once. Returns the bytes read after that line:
    feed them to the parser before anything read later.
    """
    if to not in ("N", "I"):
        raise FormatError(f"exit to 'N' (Normal) or 'I' (Init) Mode, got {to!r}")
    command = f"x {to}"
    ser.write(command.encode("ascii") + b"\r")

    def answered(buf: bytearray) -> bool:
        return _EXIT_LINE.search(buf) is not None or PROMPT in buf

    buf = _read_until(ser, answered, timeout, f"answer to {command!r}", command)
    line = _EXIT_LINE.search(buf)
    if line is None:  # still in Service Mode: the unit refused, with an error and a prompt
        _reply(command, bytes(buf[:buf.index(PROMPT)]))
        raise ServiceError(command, None, _text(bytes(buf)))
    return bytes(buf[line.end():])


CONFIRM_SAVE = b"CONFIRM SAVE(Y/N)"
BIT_RATE_SETTLE_S = 0.1  # time for a refusal of `t` (Ennn, prompt) to arrive at the old bit rate


@contextmanager
def service_mode(ser: serial.Serial, timeout: float = 3.0) -> Iterator[str]:
    """Enter Service Mode, yield its information report, and always leave it to Normal Mode.

    The unit is left with `x N` on every path out, Ctrl-C included: a unit left in Service Mode
    sends no datagrams, and a daemon reading it would see a silent sensor. If SERVICEMODE got no
    prompt, `x N` is still sent (a Normal Mode unit ignores it). If leaving fails while another
    error is on its way out, the ServiceError raised names both.
    """
    try:
        report = enter_service_mode(ser, timeout)
    except BaseException:
        _send_exit_quietly(ser)
        raise
    try:
        yield report
    except BaseException as failure:
        try:
            _drain(ser, timeout)  # the answer to an interrupted command must not be taken for the exit's
            exit_service_mode(ser, "N", timeout)
        except (Stim300Error, serial.SerialException, OSError) as exit_failure:
            raise ServiceError("x N", None, f"could not leave Service Mode ({exit_failure}) after: "
                                            f"{_describe_failure(failure)}") from failure
        raise
    exit_service_mode(ser, "N", timeout)


def _drain(ser: serial.Serial, timeout: float) -> None:
    """Read and drop bytes until the line stays quiet for ENTER_SETTLE_S (at most `timeout` s)."""
    deadline = time.monotonic() + timeout
    quiet_since = time.monotonic()
    while time.monotonic() - quiet_since < ENTER_SETTLE_S and time.monotonic() < deadline:
        if read_available(ser):
            quiet_since = time.monotonic()


def _send_exit_quietly(ser: serial.Serial) -> None:
    try:
        ser.write(b"x N\r")
    except (serial.SerialException, OSError):
        pass  # the port itself failed: there is no line to send it on


def _describe_failure(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, Stim300Error) else f"{type(exc).__name__} {exc}".strip()


def save_to_flash(ser: serial.Serial, timeout: float = 3.0) -> str:
    """Run `s`: answer the unit's CONFIRM SAVE(Y/N) with `Y`; return the text it printed.

    The protocol description says to answer with an upper-case Y, not whether a CR follows:
    Y goes alone. A refusal before the question (E004 saves exceeded) or after it (E005 save
    error) raises ServiceError.
    """
    ser.write(b"s\r")
    buf = _read_until(ser, lambda b: CONFIRM_SAVE in b or PROMPT in b, timeout, "save confirmation question", "s")
    if CONFIRM_SAVE not in buf:
        _reply("s", bytes(buf[:buf.index(PROMPT)]))
        raise ServiceError("s", None, _text(bytes(buf)))
    asked = bytes(buf[:buf.index(CONFIRM_SAVE) + len(CONFIRM_SAVE)])
    rest = buf[len(asked):]
    ser.write(b"Y")
    rest += _read_until(ser, lambda b: PROMPT in rest + b, timeout, "prompt after the save", "s")
    return _reply("s", asked + bytes(rest[:rest.index(PROMPT)]))


def change_bit_rate(ser: serial.Serial, command: str, bit_rate_bps: int, timeout: float = 3.0) -> str:
    """Run a `t` command and follow the unit to `bit_rate_bps`; return the `i` report read there.

    A user-defined rate is made by dividing the unit's clock, so the unit runs near, not at, the
    requested rate; a UART reads across the small difference, and the caller sets the port to the
    rate the report then names.

    The protocol description does not say at which rate the answer to `t` comes. A refusal is
    awaited at the old rate for BIT_RATE_SETTLE_S; then the port switches and `i` must answer at
    the new rate. If it does not, the port goes back, ends the unit's input line with a CR, and
    asks again at the old rate: an answer there means the unit kept its rate (ServiceError);
    silence at both rates, ServiceTimeout.
    """
    old_bps = ser.baudrate
    ser.write(command.encode("ascii") + b"\r")
    time.sleep(BIT_RATE_SETTLE_S)
    answer = bytes(ser.read(ser.in_waiting))
    if PROMPT in answer:
        _reply(command, answer[:answer.index(PROMPT)])
    ser.baudrate = bit_rate_bps
    ser.reset_input_buffer()
    try:
        return service_command(ser, "i", timeout)
    except ServiceTimeout:
        ser.baudrate = old_bps
        ser.write(b"\r")  # ends the line of junk the unit may have made of the `i` sent at the other rate
        _drain(ser, timeout)
        service_command(ser, "i", timeout)
        raise ServiceError(command, None, f"the unit still answers at {old_bps} bit/s, "
                                          f"not at {bit_rate_bps} bit/s") from None
