"""A STIM300 behind a pseudo-terminal, written from the protocol description: Normal Mode
datagrams (the requests N, I, C, T answered in place of the next datagrams), and Service Mode
entered with SERVICEMODE (characters echoed, CR '>' prompt, `Ennn` errors, the `i` report with
the trims in force, `m d u f t r` changes, `b` bias trims, `s` with CONFIRM SAVE(Y/N) and a
count of flash saves, `x N` / `x I` back to datagrams).

The code under test opens `path` as a serial port. The emulator is a UART at its own bit rate:
it reads the rate the host set on the line (TCGETS2 on the pty); what arrives at another rate
is junk (0xFF) in its Service Mode input line and lost in Normal Mode, and what it sends
reaches a host listening at another rate as junk, so a `t` change must be followed. The `i`
report's wording is ours (the description lists its content only): NAME = VALUE lines in
Latin-1 (deg and +- are the bytes 0xB0, 0xB1, as a real unit prints them), the form
`stim300.configure` reads.

Bias trims (STIM300 datasheet TS1524 rev.31, 7.5.2.3, 9.2): volatile in `state` until `s` saves
them with the rest to `flash`; a value beyond the triad's range (`calibd.spec`) is clamped and
answered E008; `power_cycle()` starts the unit again from flash. Normal Mode output is the
sample source plus the trims in force (`with_trims`), so a test builds a trimmed capture by the
same code. The source is random exact samples, or `samples` (SAMPLE_DTYPE, in the state's
format) streamed again and again with the unit's own counter.
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

from calibd import spec
from captures import exact_samples
from stim300.codec import encode_samples
from stim300.configure import DATAGRAM_CODES, LPF_CODES
from stim300.protocol import (NORMAL_LAYOUTS, SAMPLE_RATES_HZ, STANDARD_BIT_RATES, AccUnit, Format, GyroUnit,
                              Status)
from stim300.special import BiasTrimOffset, Configuration, PartNumber, SerialNumber, encode_special
from stim300.trim import trim_lsb

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
          7: "DATAGRAM TOO LONG FOR SAMPLE RATE AND BIT RATE", 8: "BIAS TRIM CLIPPED"}
SERIAL_NUMBER = "N25582405002002"
PART_NUMBER = "84167-4400003-321"
ACC_RANGE_G = 10
STANDARD_GRAVITY = 9.80665  # m/s^2 per g: the velocity units
START_UP_DATAGRAMS = 40  # datagrams flagged START_UP after a power cycle


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
    gyro_trim_deg_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    acc_trim_g: tuple[float, float, float] = (0.0, 0.0, 0.0)
    incl_trim_g: tuple[float, float, float] = (0.0, 0.0, 0.0)
    trim_reference: int = 0

    @property
    def rate_hz(self) -> int | None:
        return None if self.sample_rate_code == EXTERNAL_TRIGGER_CODE else SAMPLE_RATES_HZ[self.sample_rate_code]

    @property
    def format(self) -> Format:
        return Format(datagram_id=self.datagram_id, crlf=self.crlf, sample_rate_hz=self.rate_hz or 2000,
                      gyro_unit=self.gyro_unit, acc_unit=self.acc_unit, incl_unit=self.incl_unit)

    def trims(self) -> dict[str, tuple[float, float, float]]:
        return {"gyro": self.gyro_trim_deg_s, "acc": self.acc_trim_g, "incl": self.incl_trim_g}

    def fits(self) -> bool:
        """A datagram at the sample rate fits the bit rate (8N1: 10 bits a byte)."""
        wire = NORMAL_LAYOUTS[self.datagram_id].wire_length(self.crlf)
        return wire * 10 * (self.rate_hz or 2000) <= self.bit_rate_bps


class SensorEmulator(threading.Thread):
    """Start it, point the code at `path`, `stop()` it. `mode` is "normal" or "service";
    `state` the volatile configuration, `flash` the saved one; `lines` every command line
    received in Service Mode; `refuse` maps a command line to an error code it answers with,
    `silent` holds command lines it never answers; `samples` the source of Normal Mode data
    (None: random exact samples); `datagram_tail` the bytes that end the datagram in progress
    before the SERVICEMODE report; `burst` the datagrams sent every 10 ms (4: 400 a second, a
    125 Hz unit's stream 3.2 times faster than the sensor's)."""

    def __init__(self, state: State = State(), saves_left: int = 9998, refuse: dict[str, int] | None = None,
                 silent: tuple[str, ...] = (), samples: np.ndarray | None = None, datagram_tail: bytes = b"",
                 burst: int = 4):
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
        self.samples = samples
        self.datagram_tail = datagram_tail
        self.burst = burst
        self._requests: list[bytes] = []  # special datagrams asked for in Normal Mode, sent next
        self._starting = 0  # datagrams still to be flagged START_UP
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
                self._datagrams(self.burst)
                next_datagrams = time.monotonic() + 0.01

    def stop(self) -> None:
        self._halt.set()
        self.join(5)
        for fd in (self.master, self.slave):
            os.close(fd)

    def power_cycle(self) -> None:
        """Power off and on: the flash settings (trims included) come back, volatile ones are
        lost; the power-up datagrams go out, then data flagged START_UP for a while."""
        self.state = self.flash
        self.mode = "normal"
        self._line.clear()
        self._confirming = False
        self._counter = 0
        self._starting = START_UP_DATAGRAMS
        self._requests = [encode_special(item, self.state.crlf) for item in
                          (PartNumber(PART_NUMBER, "K"), SerialNumber(SERIAL_NUMBER), self._configuration())]

    def _datagrams(self, n: int) -> None:
        """n datagrams' time: the special datagrams asked for take the place of the first ones."""
        state, fmt = self.state, self.state.format
        step = 2000 // fmt.sample_rate_hz
        while self._requests and n:
            self.send(self._requests.pop(0))
            self._counter = (self._counter + step) % 256
            n -= 1
        if not n:
            return
        samples = self._source(n, fmt)
        samples["counter"] = (self._counter + step * np.arange(n)) % 256
        if self._starting:
            flagged = min(n, self._starting)
            for cluster in ("gyro", "acc", "incl"):
                samples["status_" + cluster][:flagged] |= np.uint8(Status.START_UP)
            self._starting -= flagged
        self._counter = (int(samples["counter"][-1]) + step) % 256
        self.send(encode_samples(with_trims(samples, state, fmt), state.datagram_id, fmt, state.crlf).tobytes())
        self.datagrams_sent += n

    def _source(self, n: int, fmt: Format) -> np.ndarray:
        if self.samples is None:
            return exact_samples(n, fmt, self.state.datagram_id, np.random.default_rng(self.datagrams_sent))
        return self.samples[(self.datagrams_sent + np.arange(n)) % len(self.samples)].copy()

    def _configuration(self) -> Configuration:
        s = self.state
        layout = NORMAL_LAYOUTS[s.datagram_id]
        return Configuration.build(
            sample_rate_hz=s.rate_hz, bit_rate_bps=s.bit_rate_bps if s.bit_rate_bps in STANDARD_BIT_RATES else None,
            acc_range_g=ACC_RANGE_G, crlf=s.crlf, acc_included="acc" in layout.clusters,
            incl_included="incl" in layout.clusters, temp_included=bool(layout.temperatures),
            aux_in_datagram=layout.aux == "pps", gyro_unit=s.gyro_unit, acc_unit=s.acc_unit, incl_unit=s.incl_unit,
            gyro_lpf_hz=s.gyro_lpf_hz, acc_lpf_hz=s.acc_lpf_hz, incl_lpf_hz=s.incl_lpf_hz,
            line_termination=s.line_termination)

    def _bias_trim_offset(self) -> BiasTrimOffset:
        """What the T datagram carries now."""
        s = self.state
        return BiasTrimOffset(s.gyro_trim_deg_s, s.acc_trim_g, s.incl_trim_g, s.trim_reference, self.saves_left)

    def _request(self, line: bytes) -> None:
        """A Normal Mode request (no echo): its special datagram replaces the next datagram."""
        crlf = self.state.crlf
        answer = {b"N": lambda: PartNumber(PART_NUMBER, "K"), b"I": lambda: SerialNumber(SERIAL_NUMBER),
                  b"C": self._configuration, b"T": self._bias_trim_offset}.get(line)
        if answer is not None:
            self._requests.append(encode_special(answer(), crlf, ACC_RANGE_G))

    # ------------------------------------------------------------ Normal and Service Mode

    def _byte(self, byte: int) -> None:
        if self.mode == "normal":  # commands are not echoed; only SERVICEMODE matters here
            if byte == 0x0D:
                if self._line == b"SERVICEMODE":
                    self.mode = "service"
                    self.entries += 1
                    self.send(self.datagram_tail + report(self.state, self.saves_left) + PROMPT)
                else:
                    self._request(bytes(self._line))
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
            handler = {"i": self._info, "b": self._bias_trim, "m": self._rate, "d": self._datagram, "u": self._unit,
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
            raise Refusal(3)  # the sub-reports (i m, i b, ...) are not emulated
        return report(self.state, self.saves_left)

    def _bias_trim(self, params) -> bytes:
        """`b v` (every axis), `b v,<g|a|i>` (a triad), `b delta,<g|a|i>,<x|y|z>` (added to the
        axis), `b refinfo,r`. Each offset is kept as a count of the T datagram's LSB, clamped to
        its triad's range; a clamp keeps the clamped value and answers E008."""
        if not 1 <= len(params) <= 3:
            raise Refusal(2)
        if params[1:] == ["r"]:
            if not params[0].isdigit() or int(params[0]) >= 1 << 32:
                raise Refusal(3)
            return self._change(trim_reference=int(params[0]))
        try:
            value = float(params[0])
        except ValueError:
            raise Refusal(3) from None
        groups = [GROUP_LETTERS.get(params[1])] if len(params) > 1 else list(GROUP_LETTERS.values())
        axes = ["xyz".find(params[2])] if len(params) > 2 else [0, 1, 2]
        if None in groups or -1 in axes or not np.isfinite(value):
            raise Refusal(3)
        trims, clamped = self.state.trims(), False
        for group in groups:
            lsb = trim_lsb(group, ACC_RANGE_G)
            limit = spec.triads(ACC_RANGE_G)[group].bias_trim_range
            values = list(trims[group])
            for axis in axes:
                wanted = values[axis] + value if len(params) == 3 else value
                values[axis] = round(min(max(wanted, -limit), limit) / lsb) * lsb
                clamped |= abs(wanted) > limit
            trims[group] = tuple(values)
        self._change(gyro_trim_deg_s=trims["gyro"], acc_trim_g=trims["acc"], incl_trim_g=trims["incl"])
        if clamped:
            raise Refusal(8)
        return b""

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


def with_trims(samples: np.ndarray, state: State, fmt: Format) -> np.ndarray:
    """The samples as the unit outputs them with `state`'s trims: each offset (deg/s, g) added
    after compensation, in the output's unit (an angle or velocity unit gets it times the sample
    period, in m/s where the unit is; an integrated unit's running sum is not emulated)."""
    out = samples.copy()
    for group, unit in (("gyro", fmt.gyro_unit), ("acc", fmt.acc_unit), ("incl", fmt.incl_unit)):
        out[group] += np.asarray(state.trims()[group]) * _per_sample(unit, fmt.sample_rate_hz)
    return out


def _per_sample(unit: GyroUnit | AccUnit, rate_hz: int) -> float:
    """Output units per deg/s or g of offset."""
    if isinstance(unit, GyroUnit):
        return 1.0 / rate_hz if unit.is_angle else 1.0
    if not unit.is_velocity:
        return 1.0
    in_m_s = unit in (AccUnit.INCREMENTAL_VELOCITY, AccUnit.INTEGRATED_VELOCITY_MS)
    return (STANDARD_GRAVITY if in_m_s else 1.0) / rate_hz


def trim_lines(s: State) -> list[str]:
    """The `i` report's lines of the trims in force and their reference."""
    def values(trim):
        return ", ".join(f"{v:+.9f}" for v in trim)
    return [f"GYRO TRIM [\u00b0/s] = {values(s.gyro_trim_deg_s)}",
            f"ACC TRIM [g] = {values(s.acc_trim_g)}",
            f"INCL TRIM [g] = {values(s.incl_trim_g)}",
            f"TRIM REFERENCE = {s.trim_reference}"]


def report(s: State, saves_left: int) -> bytes:
    """The `i` report of a unit in state `s`: NAME = VALUE lines ending in CR (no prompt)."""
    layout = NORMAL_LAYOUTS[s.datagram_id]
    content = ", ".join(["RATE"] + [c.upper() for c in layout.clusters[1:]]
                        + (["TEMP"] if layout.temperatures else []) + (["PPS"] if layout.aux == "pps" else []))
    lines = [
        "PRODUCT = STIM300",
        "PART NUMBER = 84167-4400003-321 REV K",
        f"SERIAL NUMBER = {SERIAL_NUMBER}",
        "FW CONFIG = SWD12345 REV 2",
        f"SAMPLE RATE [Hz] = {s.rate_hz or 'EXTERNAL TRIGGER'}",
        f"DATAGRAM = 0x{s.datagram_id:02X} {content}",
        f"DATAGRAM TERMINATION = {'CRLF' if s.crlf else 'NONE'}",
        f"GYRO OUTPUT UNIT = {GYRO_UNIT_TEXT[s.gyro_unit]}",
        f"ACC OUTPUT UNIT = {ACC_UNIT_TEXT[s.acc_unit]}",
        f"INCL OUTPUT UNIT = {ACC_UNIT_TEXT[s.incl_unit]}",
        *(f"{group.upper()} LP FILTER -3dB FREQUENCY X,Y,Z [Hz] = "
          + ", ".join(map(str, getattr(s, group + "_lpf_hz"))) for group in ("gyro", "acc", "incl")),
        "GYRO RANGE [deg/s] = \u00b1400",
        f"ACC RANGE [g] = \u00b1{ACC_RANGE_G}",
        *trim_lines(s),
        f"BIT RATE [bits/s] = {s.bit_rate_bps}",
        "STOP BITS = 1",
        "PARITY = NONE",
        f"LINE TERMINATION = {'ON' if s.line_termination else 'OFF'}",
        f"REMAINING FLASH SAVES = {saves_left}",
    ]
    return "\r".join(lines).encode("latin-1")
