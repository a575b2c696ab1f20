"""A STIM300 behind a pseudo-terminal, written from the protocol description: Normal Mode
datagrams, and Service Mode entered with SERVICEMODE (characters echoed, CR '>' prompt,
`Ennn` errors, the `i` report, `m d u f t r` changes, `s` with CONFIRM SAVE(Y/N) and a count of
flash saves, `x N` / `x I` back to datagrams).

The code under test opens `path` as a serial port. The emulator is a UART at its own bit rate:
it reads the rate the host set on the line (TCGETS2 on the pty); what arrives at another rate
is junk (0xFF) in its Service Mode input line and lost in Normal Mode, and what it sends
reaches a host listening at another rate as junk, so a `t` change must be followed. The `i`
report's wording is ours (the description lists its content only): NAME = VALUE lines, the
form `stim300.configure` reads.
"""

from __future__ import annotations

import array
import fcntl
import os
import select
import threading
import time
import tty
from dataclasses import dataclass, replace

import numpy as np

from captures import exact_samples
from stim300.codec import encode_samples
from stim300.configure import DATAGRAM_CODES, LPF_CODES
from stim300.protocol import NORMAL_LAYOUTS, SAMPLE_RATES_HZ, STANDARD_BIT_RATES, AccUnit, Format, GyroUnit

TCGETS2 = 0x802C542A  # struct termios2: c_ispeed, c_ospeed are its 10th and 11th ints
PROMPT = b"\r>"
BIT_RATE_CLOCK_HZ = 82944000  # a user-defined bit rate is this divided by the nearest integer
UART_TOLERANCE = 0.02  # a UART reads a line whose rate is this close to its own
EXTERNAL_TRIGGER_CODE = 5
GYRO_UNIT_TEXT = {GyroUnit.RATE: "ANGULAR RATE [deg/s]", GyroUnit.INCREMENTAL_ANGLE: "INCREMENTAL ANGLE [deg]",
                  GyroUnit.AVERAGE_RATE: "AVERAGE ANGULAR RATE [deg/s]",
                  GyroUnit.INTEGRATED_ANGLE: "INTEGRATED ANGLE [deg]"}
GYRO_UNIT_TEXT |= {GyroUnit(int(u) | 8): text + " DELAYED" for u, text in list(GYRO_UNIT_TEXT.items())}
ACC_UNIT_TEXT = {AccUnit.ACCELERATION: "ACCELERATION [g]", AccUnit.INCREMENTAL_VELOCITY: "INCREMENTAL VELOCITY [m/s]",
                 AccUnit.AVERAGE_ACCELERATION: "AVERAGE ACCELERATION [g]",
                 AccUnit.INTEGRATED_VELOCITY_GS: "INTEGRATED VELOCITY [g*s]",
                 AccUnit.INTEGRATED_VELOCITY_MS: "INTEGRATED VELOCITY [m/s]"}
GROUP_LETTERS = {"g": "gyro", "a": "acc", "i": "incl"}
ERRORS = {1: "UNKNOWN COMMAND", 2: "WRONG NUMBER OF PARAMETERS", 3: "INVALID PARAMETER", 4: "SAVES EXCEEDED",
          7: "DATAGRAM TOO LONG FOR SAMPLE RATE AND BIT RATE"}


class Refusal(Exception):
    def __init__(self, code: int):
        super().__init__(f"E{code:03d} {ERRORS[code]}")


@dataclass(frozen=True)
class State:
    """What the unit is set to (volatile) or holds in flash."""

    sample_rate_code: int = 4  # 2000 Hz
    datagram_id: int = 0x93
    crlf: bool = False
    gyro_unit: GyroUnit = GyroUnit.RATE
    acc_unit: AccUnit = AccUnit.ACCELERATION
    incl_unit: AccUnit = AccUnit.ACCELERATION
    gyro_lpf_hz: tuple[int, int, int] = (262, 262, 262)
    acc_lpf_hz: tuple[int, int, int] = (262, 262, 262)
    incl_lpf_hz: tuple[int, int, int] = (16, 16, 16)
    bit_rate_bps: int = 921600
    line_termination: bool = True

    @property
    def rate_hz(self) -> int | None:
        return None if self.sample_rate_code == EXTERNAL_TRIGGER_CODE else SAMPLE_RATES_HZ[self.sample_rate_code]

    def fits(self) -> bool:
        """A datagram at the sample rate fits the bit rate (8N1: 10 bits a byte)."""
        wire = NORMAL_LAYOUTS[self.datagram_id].wire_length(self.crlf)
        return wire * 10 * (self.rate_hz or 2000) <= self.bit_rate_bps


class SensorEmulator(threading.Thread):
    """Start it, point the code at `path`, `stop()` it. `mode` is "normal" or "service";
    `state` the volatile configuration, `flash` the saved one; `lines` every command line
    received in Service Mode; `refuse` maps a command line to an error code it answers with,
    `silent` holds command lines it never answers."""

    def __init__(self, state: State = State(), saves_left: int = 9998, refuse: dict[str, int] | None = None,
                 silent: tuple[str, ...] = ()):
        super().__init__(daemon=True, name="STIM300 emulator")
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.state = self.flash = state
        self.saves_left = saves_left
        self.refuse = dict(refuse or {})
        self.silent = silent
        self.mode = "normal"
        self.lines: list[str] = []
        self.entries = 0  # SERVICEMODE requests obeyed
        self.datagrams_sent = 0
        self._line = bytearray()
        self._confirming = False
        self._counter = 0
        self._halt = threading.Event()

    # ------------------------------------------------------------ the line

    def host_bps(self) -> int:
        buf = array.array("i", [0] * 64)
        fcntl.ioctl(self.slave, TCGETS2, buf)
        return buf[10]

    def in_step(self) -> bool:
        """The host's port runs near enough the unit's bit rate to understand each other."""
        return abs(self.host_bps() - self.state.bit_rate_bps) <= UART_TOLERANCE * self.state.bit_rate_bps

    def send(self, data: bytes) -> None:
        """As the host hears it: junk if it listens at another rate; lost if nobody reads."""
        if not self.in_step():
            data = b"\xff" * len(data)
        view = memoryview(data)
        deadline = time.monotonic() + 1.0
        while view and time.monotonic() < deadline:
            try:
                view = view[os.write(self.master, view):]
            except BlockingIOError:
                time.sleep(0.001)

    def run(self) -> None:
        next_datagrams = time.monotonic()
        while not self._halt.is_set():
            if select.select([self.master], [], [], 0.005)[0]:
                try:
                    data = os.read(self.master, 4096)
                except OSError:
                    data = b""
                if data and not self.in_step():
                    data = b"\xff" * len(data) if self.mode == "service" else b""  # junk in the input line
                for byte in data:
                    self._byte(byte)
            if self.mode == "normal" and time.monotonic() >= next_datagrams:
                self._datagrams(4)
                next_datagrams = time.monotonic() + 0.01

    def stop(self) -> None:
        self._halt.set()
        self.join(5)
        for fd in (self.master, self.slave):
            os.close(fd)

    def _datagrams(self, n: int) -> None:
        state = self.state
        fmt = Format(datagram_id=state.datagram_id, crlf=state.crlf, sample_rate_hz=state.rate_hz or 2000,
                     gyro_unit=state.gyro_unit, acc_unit=state.acc_unit, incl_unit=state.incl_unit)
        samples = exact_samples(n, fmt, state.datagram_id, np.random.default_rng(self.datagrams_sent),
                                counter0=self._counter)
        self._counter = (int(samples["counter"][-1]) + 2000 // fmt.sample_rate_hz) % 256
        self.send(encode_samples(samples, state.datagram_id, fmt, state.crlf).tobytes())
        self.datagrams_sent += n

    # ------------------------------------------------------------ Normal and Service Mode

    def _byte(self, byte: int) -> None:
        if self.mode == "normal":  # commands are not echoed; only SERVICEMODE matters here
            if byte == 0x0D:
                if self._line == b"SERVICEMODE":
                    self.mode = "service"
                    self.entries += 1
                    self.send(report(self.state, self.saves_left) + PROMPT)
                self._line.clear()
            else:
                self._line.append(byte)
            return
        if self._confirming:
            self._confirming = False
            self.send(bytes([byte]))
            if byte == ord("Y"):
                self.flash = self.state
                self.saves_left -= 1
                self.send(b"\rCONFIGURATION SAVED" + PROMPT)
            else:
                self.send(b"\rNOT SAVED" + PROMPT)
            return
        self.send(bytes([byte]))  # echo, CR included
        if byte == 0x08:
            del self._line[-1:]
        elif byte == 0x0D:
            line = self._line.decode("ascii", "replace")
            self._line.clear()
            self.lines.append(line)
            self._command(line)
        else:
            self._line.append(byte)

    def _command(self, line: str) -> None:
        name, _, args = line.partition(" ")
        params = args.split(",") if args else []
        if line in self.silent:
            return
        try:
            if line in self.refuse:
                raise Refusal(self.refuse[line])
            if name == "x":
                return self._exit(params)
            if name == "s":
                if params:
                    raise Refusal(2)
                if self.saves_left <= 0:
                    raise Refusal(4)
                self._confirming = True
                return self.send(b"CONFIRM SAVE(Y/N)")
            if name == "t":
                return self._bit_rate(params)
            handler = {"i": self._info, "m": self._rate, "d": self._datagram, "u": self._unit,
                       "f": self._filter, "r": self._line_termination, "": lambda p: b""}.get(name)
            if handler is None:
                raise Refusal(1)
            self.send(handler(params) + PROMPT)
        except Refusal as refusal:
            self.send(str(refusal).encode() + PROMPT)

    def _change(self, **changes) -> bytes:
        state = replace(self.state, **changes)
        if not state.fits():
            raise Refusal(7)
        self.state = state
        return b""

    def _exit(self, params) -> None:
        if params not in (["N"], ["I"]):
            raise Refusal(3)  # lower-case n / i ask CONFIRM EXIT(Y/N): not emulated
        if params == ["I"]:
            self.state = self.flash  # Init Mode: the unit starts over from flash
        self.mode = "normal"
        self.send(f"SYSTEM RETURNING TO {'NORMAL' if params == ['N'] else 'INIT'} MODE\r".encode())

    def _info(self, params) -> bytes:
        if params:
            raise Refusal(3)  # the sub-reports (i m, i d, ...) are not emulated
        return report(self.state, self.saves_left)

    def _rate(self, params) -> bytes:
        if len(params) != 1:
            raise Refusal(2)
        if params[0] not in "012345" or len(params[0]) != 1:
            raise Refusal(3)
        return self._change(sample_rate_code=int(params[0]))

    def _datagram(self, params) -> bytes:
        if len(params) != 2:
            raise Refusal(2)
        codes = {code: datagram_id for datagram_id, code in DATAGRAM_CODES.items()}
        if params[0] not in codes or params[1] not in ("0", "1"):
            raise Refusal(3)
        return self._change(datagram_id=codes[params[0]], crlf=params[1] == "1")

    def _unit(self, params) -> bytes:
        if len(params) != 2:
            raise Refusal(2)
        group, code = params
        try:
            value = int(code, 16)
            unit = {"g": GyroUnit, "a": AccUnit, "i": AccUnit}[group](value)
        except (KeyError, ValueError):
            raise Refusal(3) from None
        return self._change(**{GROUP_LETTERS[group] + "_unit": unit})

    def _filter(self, params) -> bytes:
        if not 1 <= len(params) <= 3:
            raise Refusal(2)
        hz = {code: hz for hz, code in LPF_CODES.items()}.get(int(params[0]) if params[0].isdigit() else -1)
        groups = [GROUP_LETTERS.get(params[1])] if len(params) > 1 else list(GROUP_LETTERS.values())
        axes = ["xyz".find(params[2])] if len(params) > 2 else [0, 1, 2]
        if hz is None or None in groups or -1 in axes:
            raise Refusal(3)
        changes = {}
        for group in groups:
            lpf = list(getattr(self.state, group + "_lpf_hz"))
            for axis in axes:
                lpf[axis] = hz
            changes[group + "_lpf_hz"] = tuple(lpf)
        return self._change(**changes)

    def _line_termination(self, params) -> bytes:
        if params not in (["0"], ["1"]):
            raise Refusal(3)
        return self._change(line_termination=params == ["1"])

    def _bit_rate(self, params) -> None:
        """`t <code>` or `t f,<bps>`: the echo went out at the old rate, the prompt at the new."""
        user_defined = bool(params) and params[0] == "f"
        if len(params) not in ((2, 4) if user_defined else (1, 3)):
            raise Refusal(2)
        if user_defined:
            requested = int(params[1]) if params[1].isdigit() else 0
            if not 1500 <= requested <= 5184000:
                raise Refusal(3)
            bps = round(BIT_RATE_CLOCK_HZ / round(BIT_RATE_CLOCK_HZ / requested))
        elif params[0] in ("0", "1", "2", "3"):
            bps = STANDARD_BIT_RATES[int(params[0])]
        else:
            raise Refusal(3)
        self._change(bit_rate_bps=bps)
        self.send(PROMPT)


def report(s: State, saves_left: int) -> bytes:
    """The `i` report of a unit in state `s`: NAME = VALUE lines ending in CR (no prompt)."""
    layout = NORMAL_LAYOUTS[s.datagram_id]
    content = ", ".join(["RATE"] + [c.upper() for c in layout.clusters[1:]]
                        + (["TEMP"] if layout.temperatures else []) + (["PPS"] if layout.aux == "pps" else []))
    lines = [
        "PRODUCT = STIM300",
        "PART NUMBER = 84167-4400003-321 REV K",
        "SERIAL NUMBER = N25582405002002",
        "FW CONFIG = SWD12345 REV 2",
        f"SAMPLE RATE [Hz] = {s.rate_hz or 'EXTERNAL TRIGGER'}",
        f"DATAGRAM = 0x{s.datagram_id:02X} {content}",
        f"DATAGRAM TERMINATION = {'CRLF' if s.crlf else 'NONE'}",
        f"GYRO OUTPUT UNIT = {GYRO_UNIT_TEXT[s.gyro_unit]}",
        f"ACC OUTPUT UNIT = {ACC_UNIT_TEXT[s.acc_unit]}",
        f"INCL OUTPUT UNIT = {ACC_UNIT_TEXT[s.incl_unit]}",
        *(f"{group.upper()} LP FILTER -3dB FREQUENCY X,Y,Z [Hz] = "
          + ", ".join(map(str, getattr(s, group + "_lpf_hz"))) for group in ("gyro", "acc", "incl")),
        "GYRO RANGE [deg/s] = 400",
        "ACC RANGE [g] = 10",
        f"BIT RATE [bits/s] = {s.bit_rate_bps}",
        "STOP BITS = 1",
        "PARITY = NONE",
        f"LINE TERMINATION = {'ON' if s.line_termination else 'OFF'}",
        f"REMAINING FLASH SAVES = {saves_left}",
    ]
    return "\r".join(lines).encode()
