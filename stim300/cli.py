"""`stim300 decode | info | record | config`: captures to tables, a capture's health, raw
recording, the sensor's configuration through Service Mode.

Bad input (missing or empty files, bytes that are not STIM300, unknown option values,
unwritable outputs) ends with one line on stderr and a non-zero exit, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import mmap
import os
import sys
import time
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np

from .cliutil import CommandParser, not_an_input, open_regular, path_arg, run_command, write_error
from .errors import UsageError
from .protocol import (ACC_RANGE_LSB_EXP, COUNTER_MODULUS, DEFAULT_BIT_RATE, INTERNAL_RATE_HZ, NORMAL_LAYOUTS,
                       SAMPLE_RATES_HZ, STANDARD_BIT_RATES, AccUnit, Format, GyroUnit, Status)

if TYPE_CHECKING:
    from .capture import StreamInfo
    from .special import Configuration

# A command imports the decoders, the writers and Service Mode in its own body, so that
# `stim300 --version` and `--help` cost about numpy's import (benchmarks/startup.py).

AXES = "xyz"
GYRO_UNITS = {"rate": GyroUnit.RATE, "incremental": GyroUnit.INCREMENTAL_ANGLE,
              "average": GyroUnit.AVERAGE_RATE, "integrated": GyroUnit.INTEGRATED_ANGLE}
GYRO_UNITS |= {name + "-delayed": GyroUnit[unit.name + "_DELAYED"] for name, unit in GYRO_UNITS.items()}
ACC_UNITS = {"acceleration": AccUnit.ACCELERATION, "incremental": AccUnit.INCREMENTAL_VELOCITY,
             "average": AccUnit.AVERAGE_ACCELERATION, "integrated-gs": AccUnit.INTEGRATED_VELOCITY_GS,
             "integrated-ms": AccUnit.INTEGRATED_VELOCITY_MS}


def _datagram_id(text: str) -> int:
    try:
        value = int(text, 16)
    except ValueError:
        value = -1
    if value not in NORMAL_LAYOUTS:
        known = ", ".join(f"0x{i:02X}" for i in sorted(NORMAL_LAYOUTS))
        raise argparse.ArgumentTypeError(f"unknown normal datagram id {text!r} (known: {known})")
    return value


def _choice(table: dict):
    def parse(text: str):
        if text not in table:
            raise argparse.ArgumentTypeError(f"{text!r} is not one of {', '.join(map(str, table))}")
        return table[text]
    return parse


def _add_format_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("format when the capture has no configuration datagram")
    g.add_argument("--datagram", type=_datagram_id, help="normal datagram id, e.g. 0x93 (default: detect)")
    g.add_argument("--crlf", choices=("yes", "no", "detect"), default="detect", help="CR LF termination")
    g.add_argument("--rate", type=_choice({str(r): r for r in SAMPLE_RATES_HZ}),
                   help="sample rate in Hz (default: infer the counter step from the data)")
    g.add_argument("--gyro-unit", type=_choice(GYRO_UNITS), default=GyroUnit.RATE, metavar="UNIT",
                   help=f"{', '.join(GYRO_UNITS)} (default rate)")
    g.add_argument("--acc-unit", type=_choice(ACC_UNITS), default=AccUnit.ACCELERATION, metavar="UNIT",
                   help=f"{', '.join(ACC_UNITS)} (default acceleration)")
    g.add_argument("--incl-unit", type=_choice(ACC_UNITS), default=AccUnit.ACCELERATION, metavar="UNIT",
                   help="as --acc-unit")
    g.add_argument("--acc-range", type=_choice({str(r): r for r in ACC_RANGE_LSB_EXP}), default=10,
                   metavar="G", help=f"accelerometer range in g: {', '.join(map(str, ACC_RANGE_LSB_EXP))} "
                                     "(default 10)")


def _format(args) -> Format:
    return Format(datagram_id=args.datagram, crlf={"yes": True, "no": False}.get(args.crlf),
                  sample_rate_hz=args.rate, gyro_unit=args.gyro_unit, acc_unit=args.acc_unit,
                  acc_range_g=args.acc_range, incl_unit=args.incl_unit)


@contextmanager
def _mapped(path: str):
    """The capture's bytes, memory-mapped (no copy of a large file); those of the raw channel of
    an MCAP `stim300 record` wrote (`stim300.mcaprec`)."""
    from .mcaprec import holds_capture, read_capture

    if holds_capture(path):
        yield read_capture(path)[0]
        return
    with open_regular(path) as f:
        if os.fstat(f.fileno()).st_size == 0:
            raise UsageError(f"{path}: empty file, no STIM300 data")
        try:
            m = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except OSError as exc:
            raise UsageError(f"{path}: cannot read: {exc.strerror or exc}") from None
        with m:
            yield m


def _decode(path: str, fmt: Format, reads: np.ndarray | None) -> tuple[dict[str, np.ndarray], StreamInfo]:
    """Samples (columns) and stream info; with the capture's read log (`reads`), samples carry
    host times. A given format option the data overrode is said on stderr; a given rate the
    counter contradicts is refused."""
    from .bulk import decode_columns

    with _mapped(path) as data:
        samples, info = decode_columns(data, fmt, reads=reads)
    if info.stats.datagrams == 0:
        raise UsageError(f"{path}: no STIM300 datagram found in {info.stats.bytes_in} bytes "
                         "(not a STIM300 capture, or a format the options do not describe)")
    source = "its configuration datagram says" if info.configuration else "its datagrams are"
    if fmt.datagram_id is not None and info.format.datagram_id != fmt.datagram_id:
        print(f"stim300: {path}: --datagram 0x{fmt.datagram_id:02X} not used: {source} "
              f"0x{info.format.datagram_id:02X}", file=sys.stderr)
    if fmt.sample_rate_hz is not None and info.rate_hz != fmt.sample_rate_hz:
        print(f"stim300: {path}: --rate {fmt.sample_rate_hz} not used: {source} {info.rate_words()}", file=sys.stderr)
    elif fmt.sample_rate_hz is not None:
        _check_given_rate(path, fmt.sample_rate_hz, samples["counter"])
    return samples, info


def _check_given_rate(path: str, rate_hz: int, counter: np.ndarray) -> None:
    """Refuse a --rate the counter contradicts: 2000 Hz given for 125 Hz data would count 15 lost
    samples at every datagram. The counter's most common step is its rate (a restart or a loss
    makes other steps, rarely)."""
    steps = np.bincount(np.diff(counter.astype(np.int64)) % COUNTER_MODULUS, minlength=COUNTER_MODULUS)
    steps[0] = 0  # a stuck counter says nothing of the rate
    if not steps.any():
        return
    step = int(np.argmax(steps))
    if step != INTERNAL_RATE_HZ // rate_hz:
        seen = f"{INTERNAL_RATE_HZ // step} Hz" if INTERNAL_RATE_HZ // step in SAMPLE_RATES_HZ else "no STIM300 rate"
        raise UsageError(f"{path}: --rate {rate_hz} disagrees with the datagram counter, which mostly steps by "
                         f"{step} ({seen}): give the capture's rate or leave --rate out")


def columns(samples, time_s: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Output columns: the stream time `time_s` (from the counter) when given, the host read time
    when the capture has a read log, then those of the blocks some datagram of the capture
    carries, in a fixed order."""
    ids = np.unique(samples["datagram_id"])
    layouts = [NORMAL_LAYOUTS[int(i)] for i in ids]
    clusters = [c for c in ("gyro", "acc", "incl") if any(c in lay.clusters for lay in layouts)]
    temps = [c for c in ("gyro", "acc", "incl") if any(c in lay.temperatures for lay in layouts)]
    aux = any(lay.aux for lay in layouts)
    out = {"counter": samples["counter"], "latency_us": samples["latency_us"]}
    if len(samples["t_host"]) and np.isfinite(samples["t_host"]).all():  # the capture has a read log
        out = {"t_host_s": samples["t_host"]} | out
    if time_s is not None:
        out = {"t_s": time_s} | out
    for block in clusters + ["temp_" + c for c in temps]:
        for k, axis in enumerate(AXES):
            out[f"{block}_{axis}"] = samples[block][:, k]  # contiguous in decode_columns' columns
    if aux:
        out["aux"] = samples["aux"]
    for block in clusters + ["temp_" + c for c in temps] + (["aux"] if aux else []):
        out["status_" + block] = samples["status_" + block]
    return out


def column_units(names, fmt: Format) -> dict[str, str]:
    units = fmt.units()
    result = {}
    for name in names:
        block = name.split("_")[0] if not name.startswith("temp_") else "temp"
        if name in ("t_s", "t_host_s"):
            result[name] = "s"
        elif name.startswith("status_") or name == "counter":
            result[name] = "1"
        elif name == "latency_us":
            result[name] = "us"
        elif name == "aux":
            pps = fmt.datagram_id is not None and NORMAL_LAYOUTS[fmt.datagram_id].aux == "pps"
            result[name] = units["pps" if pps else "aux"]
        else:
            result[name] = units[block]
    return result


@contextmanager
def _output(path: str):
    """`atomic_file` for a table that can be made again (no sync), with one-line errors."""
    from .atomic import atomic_file

    try:
        with atomic_file(path, durable=False) as f:
            yield f
    except OSError as exc:
        raise write_error(path, exc) from None


def _write_csv(f, cols: dict[str, np.ndarray]) -> None:
    """Text is slow (about 0.7 M rows/s of 2000 Hz columns: `stim300.csvtable`), so long tables report progress on
    stderr."""
    from .csvtable import write_rows
    from .progress import Progress

    names = list(cols)
    f.write((",".join(names) + "\n").encode())
    formats = ["%d" if cols[n].dtype.kind in "ui" else "%.6f" if n in ("t_s", "t_host_s") else "%.9g"
               for n in names]  # 9 digits round-trip float32; times to the microsecond
    rows = len(cols[names[0]])
    chunk = 100_000
    with Progress("decode: csv", rows, "rows") as bar:
        for start in range(0, rows, chunk):
            write_rows(f, [cols[n][start:start + chunk] for n in names], formats)
            bar.update(min(start + chunk, rows))


def cmd_decode(args) -> int:
    out = args.output
    if not (out.endswith(".npz") or out.endswith(".csv")):
        raise UsageError(f"{out}: output must end in .npz or .csv")
    not_an_input(out, args.capture)
    started = time.perf_counter()
    samples, info = _decode(args.capture, _format(args), _reads(args.capture))
    cols = columns(samples, sample_times(samples, info).time_s)
    units = column_units(cols, info.format)
    with _output(out) as f:
        if out.endswith(".npz"):
            np.savez(f, **cols, units=np.array(json.dumps(units)))
        else:
            _write_csv(f, cols)
    s = info.stats
    print(f"{args.capture}: {s.datagrams} datagrams -> {out} ({len(cols)} columns) in "
          f"{time.perf_counter() - started:.2f} s; crc_errors {s.crc_errors}, lost_samples {s.lost_samples}, "
          f"skipped_bytes {s.skipped_bytes} B", file=sys.stderr)
    return 0


def sample_times(samples, stream: StreamInfo):
    """The samples' stream times (`stim300.clock`: the running sum of counter steps / 2000, plus
    the whole counter cycles a read log proves lost)."""
    from .clock import counter_times

    return counter_times(samples["counter"], stream.rate_hz or INTERNAL_RATE_HZ, samples["t_host"])


def capture_info(samples, stream: StreamInfo, reads: np.ndarray | None = None) -> dict:
    """`reads`: the capture's read log, counted in `read_log_reads` (None: none), so a log
    whose reads cannot show gaps is told apart from no log."""
    s = stream.stats
    fmt = stream.format
    rate = stream.rate_hz
    times = sample_times(samples, stream) if rate else None
    checked = times is not None and times.checked
    info = {
        "datagrams": s.datagrams,
        "crc_errors": s.crc_errors,
        "lost_samples": s.lost_samples,
        "skipped_bytes": s.skipped_bytes,
        "bytes": s.bytes_in,
        "restarts": s.restarts,
        "config_changes": s.config_changes,
        "datagram_id": f"0x{fmt.datagram_id:02X}" if fmt.datagram_id is not None else None,
        "crlf": fmt.crlf,
        "sample_rate_hz": rate,
        "sample_rate": stream.rate_words(),
        "external_trigger": stream.external_trigger,
        "inferred_missing": s.inferred_missing,
        "duration_s": (s.datagrams + s.lost_samples + s.inferred_missing) / rate + times.hidden_s if rate else None,
        "hidden_gaps": times.hidden_gaps if checked else None,  # None: no host times that can show them
        "hidden_gap_s": round(times.hidden_s, 3) if checked else None,
        "read_log_reads": None if reads is None else len(reads),
        "units": {k: v for k, v in fmt.units().items()},
        "acc_range_g": fmt.acc_range_g,  # one per axis (X, Y, Z) when they differ
        "part_number": stream.part_number,
        "serial_number": stream.serial_number,
        "configuration": stream.configuration.as_dict() if stream.configuration else None,
        "status_flags": status_counts(samples),
        "warnings": list(stream.warnings),
    }
    return info


def status_counts(samples) -> dict[str, dict[str, int]]:
    """Datagrams with each status flag set, per status byte the capture carries (flags unset: omitted)."""
    present = [name for name in columns(samples) if name.startswith("status_")]
    counts = {}
    for name in present:
        column = samples[name]
        counts[name.removeprefix("status_")] = {flag.name: int(np.count_nonzero(column & flag)) for flag in Status
                                                if np.any(column & flag)}
    return counts


def _hidden_gaps(info: dict) -> str:
    """Gaps found, or why none could be: no read log, or one whose reads came faster than the
    data's own time (a capture fed faster than real time), which proves nothing lost."""
    reads = info["read_log_reads"]
    if info["hidden_gaps"] is not None:
        return f"{info['hidden_gaps']} ({info['hidden_gap_s']:.3f} s, found from the read log of {reads} reads)"
    if reads is None:
        return "- (no read log: gaps of whole counter cycles cannot be seen)"
    if info["sample_rate_hz"] is None:
        return f"- (read log of {reads} reads, but no sample rate to time the datagrams by)"
    return (f"- (read log of {reads} reads, which came faster than real time, as when a capture is replayed: "
            "they cannot show gaps of whole counter cycles)")


def _describe(info: dict, configuration: Configuration | None = None) -> str:
    def value(v, unit=""):
        return "-" if v is None else f"{v}{unit}"
    lines = [
        f"datagrams        {info['datagrams']}",
        f"datagram_id      {value(info['datagram_id'])}  (CR LF: {value(info['crlf'])})",
        f"sample rate      {info['sample_rate']}",
        f"duration         {'-' if info['duration_s'] is None else format(info['duration_s'], '.3f') + ' s'}",
        f"bytes            {info['bytes']} B",
        f"crc_errors       {info['crc_errors']}",
        f"lost_samples     {info['lost_samples']}"
        + (f" (externally triggered: {info['inferred_missing']} missing by the usual step, inferred)"
           if info["external_trigger"] else ""),
        "hidden_gaps      " + _hidden_gaps(info),
        f"skipped_bytes    {info['skipped_bytes']} B",
        f"restarts         {info['restarts']}",
        f"config_changes   {info['config_changes']}",
        "status flags     " + ("; ".join(f"{block}: " + ", ".join(f"{flag} in {n} datagrams"
                                                                  for flag, n in flags.items())
                                           for block, flags in info["status_flags"].items() if flags) or "none"),
        "units            " + ", ".join(f"{k} {v}" for k, v in info["units"].items()),
        "acc range        " + (f"{info['acc_range_g']} g" if isinstance(info["acc_range_g"], int)
                                 else " / ".join(f"{r} g" for r in info["acc_range_g"]) + " (X / Y / Z)"),
        f"part number      {value(info['part_number'])}",
        f"serial number    {value(info['serial_number'])}",
    ]
    if configuration is not None:
        lines += _configuration_lines(configuration)
    lines += [f"warning          {text}" for text in info["warnings"]]
    return "\n".join(lines)


GYRO_RANGE_DEG_S = {0: "400"}  # configuration gyro range code -> +- deg/s (the one the data sheet names)
INCL_RANGE_G = {0: "1.7"}  # inclinometer range code -> +- g


def _configuration_lines(c: Configuration) -> list[str]:
    """The configuration datagram as indented `key  value` lines, grouped by block, with units.
    A code the byte map does not define shows as read (a warning line says so)."""
    from .special import UndefinedCode

    def axes(active) -> str:
        return ", ".join(axis for axis, on in zip("XYZ", active) if on) or "none"

    def per_axis(texts) -> str:
        texts = [str(t) for t in texts]
        return texts[0] if len(set(texts)) == 1 else " / ".join(texts) + " (X / Y / Z)"

    def unit(code) -> str:
        if not hasattr(code, "name"):
            return str(code)
        return code.name.lower().replace("_", " ") + (f" ({code.symbol})" if hasattr(code, "symbol") else "")

    def code(value) -> str:
        """A code no table here names: an undefined one says so itself (UndefinedCode)."""
        return str(value) if isinstance(value, UndefinedCode) else f"code {value}"

    def hz(value) -> str:
        return f"{value} Hz" if isinstance(value, int) else str(value)

    def ranges(codes, table: dict, symbol: str) -> str:
        return per_axis(f"+-{table[c]} {symbol}" if c in table else code(c) for c in codes)

    def yes(flag: bool) -> str:
        return "yes" if flag else "no"

    content = ["gyro"] + [name for name, on in (("acc", c.acc_included), ("incl", c.incl_included),
                                                ("temperatures", c.temp_included), (c.aux_kind, c.aux_kind)) if on]
    groups = {
        "gyro": [("axes", axes(c.gyro_axes)), ("unit", unit(c.gyro_unit)),
                 ("range", ranges(c.gyro_range_codes, GYRO_RANGE_DEG_S, "deg/s")),
                 ("low-pass", per_axis(hz(v) for v in c.gyro_lpf_hz)),
                 ("g-compensation", f"preset {c.gyro_g_compensation}")],
        "acc": [("axes", axes(c.acc_axes)), ("unit", unit(c.acc_unit)),
                ("range", per_axis(f"+-{g} g" for g in c.acc_range_g)),
                ("low-pass", per_axis(hz(v) for v in c.acc_lpf_hz))],
        "incl": [("axes", axes(c.incl_axes)), ("unit", unit(c.incl_unit)),
                 ("range", ranges(c.incl_range_codes, INCL_RANGE_G, "g")),
                 ("low-pass", per_axis(hz(v) for v in c.incl_lpf_hz))],
        "serial line": [("bit rate", code(c.bit_rate_code) if isinstance(c.bit_rate_code, UndefinedCode)
                         else "user-defined (not in the datagram)" if c.bit_rate_bps is None
                         else f"{c.bit_rate_bps} bit/s"),
                        ("framing", f"{c.stop_bits} stop bit{'s' if c.stop_bits != 1 else ''}, "
                                    f"parity {unit(c.parity)}"),
                        ("termination", f"{yes(c.line_termination)} (RS422 120 ohm)"), ("CR LF", yes(c.crlf))],
        "outputs": [("datagram", f"0x{c.datagram_id:02X} ({', '.join(content)})"),
                    ("sample rate", "external trigger" if c.external_trigger else
                     f"{c.sample_rate_hz} Hz" if c.sample_rate_hz else code(c.sample_rate_code)),
                    ("pps input", f"yes, {unit(c.pps_unit)}, low-pass {hz(c.pps_lpf_hz)}" if c.has_pps_input
                     else "no (an aux input)"),
                    ("tov level", f"{'3.3' if c.tov_3v3 else '5'} V"),
                    ("at start-up", f"tov toggled: {yes(c.tov_toggle_at_startup)}, bias trim datagram: "
                                    f"{yes(c.bto_at_startup)}")],
    }
    lines = [f"configuration    revision {c.revision}, firmware {c.firmware_revision}"]
    for group, rows in groups.items():
        lines.append(f"  {group}")
        lines += [f"    {key:<15} {value}" for key, value in rows]
    return lines


def _reads(path: str) -> np.ndarray | None:
    """The capture's read log: beside it (CAPTURE.reads.npy), or in the MCAP `stim300 record` wrote."""
    from .mcaprec import holds_capture, read_capture
    from .reads import load_reads

    return read_capture(path)[1] if holds_capture(path) else load_reads(path)


def cmd_info(args) -> int:
    reads = _reads(args.capture)
    samples, stream = _decode(args.capture, _format(args), reads)
    info = capture_info(samples, stream, reads)
    print(json.dumps(info, indent=1) if args.json else _describe(info, stream.configuration))
    return 0


def cmd_record(args) -> int:
    from .port import record
    return record(args.port, args.output, baudrate=args.baud, duration_s=args.duration, max_bytes=args.max_bytes)


def _settable_datagram(text: str) -> int:
    from .configure import DATAGRAM_CODES
    try:
        value = int(text, 16)
    except ValueError:
        value = -1
    if value not in DATAGRAM_CODES:
        allowed = ", ".join(f"0x{i:02X}" for i in DATAGRAM_CODES)
        raise argparse.ArgumentTypeError(f"{text!r} is not a datagram the sensor can be set to ({allowed})")
    return value


def _bit_rate(text: str) -> int:
    from .configure import bit_rate_command
    from .errors import FormatError
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of bit/s") from None
    try:
        bit_rate_command(value)
    except FormatError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return value


def _config_rows(outcome) -> str:
    """Aligned `name: value unit` lines of the report after the changes, each change with its old value."""
    before = dict(outcome.before.rows())
    changed = outcome.changed()
    rows = outcome.after.rows()
    width = max(len(name) for name, value in rows if value) + 1
    return "\n".join(f"{name + ':':<{width}} {value}" + (f"   (was {before[name]})" if name in changed else "")
                     if value else name for name, value in rows)  # a report line that is no NAME = VALUE


def cmd_config(args) -> int:
    import serial

    from .cliutil import RunError
    from .configure import Changes, ConfigureError, configure
    from .errors import PortError, ServiceError, ServiceTimeout
    from .port import describe_error, open_serial, sigterm_as_ctrl_c
    changes = Changes(sample_rate=args.rate, datagram_id=args.datagram, crlf=args.crlf, gyro_unit=args.gyro_unit,
                      acc_unit=args.acc_unit, incl_unit=args.incl_unit, gyro_lpf_hz=args.gyro_lpf,
                      acc_lpf_hz=args.acc_lpf, incl_lpf_hz=args.incl_lpf, bit_rate_bps=args.bit_rate)
    if args.yes and not args.save:
        raise UsageError("stim300 config: --yes answers the question --save asks: give it with --save")
    if args.save and not args.yes and not sys.stdin.isatty():
        raise UsageError("stim300 config: --save asks for confirmation on the terminal: give --yes to save without "
                         "asking")

    def confirm(report) -> bool:
        saves = ("unknown (the sensor's report does not say)" if report.remaining_saves is None
                 else f"{report.remaining_saves} saves")
        print(f"stim300 config: remaining flash saves: {saves}", file=sys.stderr)
        if args.yes:
            return True
        print("write this configuration to the sensor's flash? [y/N] ", end="", file=sys.stderr, flush=True)
        return sys.stdin.readline().strip().lower() in ("y", "yes")

    try:
        with sigterm_as_ctrl_c(), open_serial(args.port, args.baud) as ser:  # kill: back to Normal Mode too
            outcome = configure(ser, changes, args.save, confirm)
    except PortError as exc:
        raise RunError(f"stim300 config: {exc}") from None
    except ServiceTimeout as exc:
        hint = f" (is the sensor on this port, at {args.baud} bit/s? --baud)" if exc.command == "SERVICEMODE" else ""
        raise RunError(f"stim300 config: {exc}{hint}") from None
    except (ServiceError, ConfigureError) as exc:
        left = isinstance(exc, ConfigureError) or exc.command != "x N"
        raise RunError(f"stim300 config: {args.port}: {exc}" + (" (the sensor is back in Normal Mode)" if left
                                                                 else "")) from None
    except (serial.SerialException, OSError) as exc:
        raise RunError(f"stim300 config: {args.port}: {describe_error(exc)}") from None
    if args.json:
        print(json.dumps({"port": args.port, "configuration": outcome.after.as_dict(),
                          "before": outcome.before.as_dict(), "changed": outcome.changed(),
                          "applied": list(outcome.applied), "saved": outcome.saved}, indent=1))
    else:
        print(_config_rows(outcome))
    if outcome.applied:
        print(f"stim300 config: applied {'; '.join(outcome.applied)}" + (
            "" if outcome.saved else " (volatile: lost at the next reset or power-off; --save keeps them)"),
            file=sys.stderr)
    if outcome.save_declined:
        kept = "; the changes stay until the sensor is reset" if outcome.applied else ""
        raise RunError(f"stim300 config: not saved: the save was declined{kept}")
    if outcome.saved:
        print("stim300 config: saved to flash", file=sys.stderr)
    return 0


def _positive(kind):
    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not (value > 0 and math.isfinite(value)):  # nan would record forever
            raise argparse.ArgumentTypeError(f"{text!r} must be a positive finite number")
        return value
    return parse


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(prog="stim300", description="STIM300 captures: decode, inspect, record.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=CommandParser)
    p = sub.add_parser("decode", help="capture -> .npz or .csv table in physical units, with t_s (stream time "
                                      "from the datagram counter, s) and t_host_s (host read time, s; with a "
                                      "read log)")
    p.add_argument("capture")
    p.add_argument("-o", "--output", type=path_arg, required=True, help="OUT.npz or OUT.csv")
    _add_format_options(p)
    p.set_defaults(func=cmd_decode)
    p = sub.add_parser("info", help="datagrams, errors, losses, rate, duration, identity, configuration")
    p.add_argument("capture")
    p.add_argument("--json", action="store_true")
    _add_format_options(p)
    p.set_defaults(func=cmd_info)
    p = sub.add_parser("record", help="raw bytes from a serial port to a capture file")
    p.add_argument("port", help="device path (/dev/ttyUSB0) or pyserial URL")
    p.add_argument("-o", "--output", type=path_arg, required=True)
    p.add_argument("--baud", type=_positive(int), default=DEFAULT_BIT_RATE, help=f"bit/s (default {DEFAULT_BIT_RATE})")
    p.add_argument("--duration", type=_positive(float), help="seconds to record (default: until Ctrl-C)")
    p.add_argument("--max-bytes", type=_positive(int), help="stop after this many bytes")
    p.set_defaults(func=cmd_record)
    _add_config_parser(sub)
    return parser


def _add_config_parser(sub) -> None:
    from .configure import LPF_CODES, SAMPLE_RATE_CODES, USER_BIT_RATE_BPS
    p = sub.add_parser("config", help="read, and set, the sensor's configuration through Service Mode")
    p.add_argument("port", help="device path (/dev/ttyUSB0) or pyserial URL")
    p.add_argument("--baud", type=_positive(int), default=DEFAULT_BIT_RATE,
                   help=f"bit/s the sensor runs at now (default {DEFAULT_BIT_RATE})")
    p.add_argument("--json", action="store_true")
    g = p.add_argument_group("changes (volatile unless --save; each checked before the sensor is touched)")
    lpf = _choice({str(hz): hz for hz in LPF_CODES})
    g.add_argument("--rate", type=_choice({str(r): r for r in SAMPLE_RATE_CODES}), metavar="HZ",
                   help=f"sample rate: {', '.join(map(str, SAMPLE_RATE_CODES))}")
    g.add_argument("--datagram", type=_settable_datagram, help="normal datagram id, e.g. 0x93")
    g.add_argument("--crlf", type=_choice({"yes": True, "no": False}), metavar="yes|no",
                   help="CR LF at the end of each datagram")
    for group, units in (("gyro", GYRO_UNITS), ("acc", ACC_UNITS), ("incl", ACC_UNITS)):
        g.add_argument(f"--{group}-unit", type=_choice(units), metavar="UNIT", help=", ".join(units))
    for group in ("gyro", "acc", "incl"):
        g.add_argument(f"--{group}-lpf", type=lpf, metavar="HZ",
                       help=f"{group} low-pass filter -3 dB frequency: {', '.join(map(str, LPF_CODES))} Hz")
    g.add_argument("--bit-rate", type=_bit_rate, metavar="BPS",
                   help=f"{', '.join(map(str, STANDARD_BIT_RATES))}, or {'..'.join(map(str, USER_BIT_RATE_BPS))} bit/s "
                        "(the port follows)")
    g.add_argument("--save", action="store_true", help="write the configuration to flash (asks first)")
    g.add_argument("--yes", action="store_true", help="with --save: do not ask")
    p.set_defaults(func=cmd_config)


def main(argv=None) -> int:
    return run_command(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
