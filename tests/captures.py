"""What several test files build or run, in one place: small synthetic captures (exact values,
integer counts times the LSB), power-up datagrams, noise-free scenarios, a polling wait, a pty
behind a link, a terminal stand-in and this tree's commands as subprocesses. The fixtures are in
conftest.py."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
import tty
from dataclasses import replace
from pathlib import Path

import numpy as np

from stim300.codec import SAMPLE_DTYPE, encode_samples
from stim300.protocol import COUNTER_MODULUS, INTERNAL_RATE_HZ, NORMAL_LAYOUTS, Format, Status
from stim300.reads import READS_DTYPE
from stim300.special import Configuration, PartNumber, SerialNumber, encode_special
from stim300.stream import StreamParser

ROOT = Path(__file__).resolve().parents[1]
SYSTEMD_ENV = ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "JOURNAL_STREAM")


def exact_samples(n: int, fmt: Format, datagram_id: int, rng: np.random.Generator, counter0: int = 0) -> np.ndarray:
    """n samples whose every value the sensor can represent, counters stepping at the sample rate."""
    layout = NORMAL_LAYOUTS[datagram_id]
    scales = fmt.scales()
    s = np.zeros(n, SAMPLE_DTYPE)
    s["t_host"] = np.nan
    s["datagram_id"] = datagram_id
    for name in ("gyro", "acc", "incl"):
        if name in layout.clusters:
            s[name] = rng.integers(-(1 << 23), 1 << 23, (n, 3)) * scales[name]
            s["status_" + name] = rng.choice([0, 0, 0, Status.START_UP, Status.OVERLOAD | Status.X], n)
        else:
            s[name] = np.nan
    for name in ("gyro", "acc", "incl"):
        if name in layout.temperatures:
            s["temp_" + name] = rng.integers(-(1 << 15), 1 << 15, (n, 3)) * scales["temp"]
            s["status_temp_" + name] = rng.integers(0, 256, n)
        else:
            s["temp_" + name] = np.nan
    if layout.aux:
        lo, hi = (0, 1 << 24) if layout.aux == "pps" and fmt.pps_unsigned else (-(1 << 23), 1 << 23)
        s["aux"] = rng.integers(lo, hi, n) * scales[layout.aux]
        s["status_aux"] = rng.integers(0, 256, n)
    else:
        s["aux"] = np.nan
    step = INTERNAL_RATE_HZ // (fmt.sample_rate_hz or INTERNAL_RATE_HZ)
    s["counter"] = (counter0 + step * np.arange(n)) % COUNTER_MODULUS
    s["latency_us"] = rng.integers(0, 1 << 16, n)
    return s


def capture(n: int, datagram_id: int = 0xA7, crlf: bool = False, rate: int = 2000, seed: int = 0,
            **units) -> tuple[bytes, np.ndarray, Format]:
    """Bytes of n normal datagrams, the samples they carry, and their format."""
    fmt = Format(datagram_id=datagram_id, crlf=crlf, sample_rate_hz=rate, **units)
    samples = exact_samples(n, fmt, datagram_id, np.random.default_rng(seed))
    return encode_samples(samples, datagram_id, fmt, crlf).tobytes(), samples, fmt


def same_samples(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal in every field but the host timestamp; NaN equals NaN."""
    if len(a) != len(b):
        return False
    for name in SAMPLE_DTYPE.names:
        if name != "t_host" and not np.array_equal(a[name], b[name], equal_nan=a[name].dtype.kind == "f"):
            return False
    return True


def power_up(config: Configuration, part: str = "84167-4400003-321", serial: str = "N25582405002002") -> bytes:
    """What the sensor sends when it starts, before its first normal datagram: part number,
    serial number, configuration."""
    return (encode_special(PartNumber(part, "K"), config.crlf) + encode_special(SerialNumber(serial), config.crlf)
            + encode_special(config, config.crlf))


def stream_decode(data: bytes, cuts=(), fmt: Format | None = None, together=()) -> tuple[np.ndarray, StreamParser]:
    """The stream parser fed `data` in reads cut at `cuts` (read k returned at time k s): its
    samples and the parser. Each read is fed on its own, or with `together` (the indices of
    reads that start a group), each group of reads at once (`StreamParser.feed_reads`)."""
    parser = StreamParser(fmt)
    edges = [0, *sorted(set(cuts)), len(data)]
    starts = sorted({0, *together, len(edges) - 1}) if together else range(len(edges))
    parts = []
    for first, stop in zip(starts, starts[1:]):
        if not together:
            parts.append(parser.feed(data[edges[first]:edges[stop]], float(first)))
            continue
        reads = np.empty(stop - first, READS_DTYPE)
        reads["end"] = np.array(edges[first + 1:stop + 1]) - edges[first]
        reads["t_host_s"] = np.arange(first, stop)
        parts.append(parser.feed_reads(data[edges[first]:edges[stop]], reads))
    parts.append(parser.finish())
    return np.concatenate(parts), parser


def quiet(scenario, **truth):
    """No noise, fully warmed up (biases at their settled values), `truth` changed as given."""
    return replace(scenario, noise=replace(scenario.noise, enabled=False),
                   warmup=replace(scenario.warmup, power_on_s=1e7), truth=replace(scenario.truth, **truth))


def with_sense(scenario, sense: int):
    """Every turn of the scenario in one sense: its angle's size with the sign of `sense` (+1 or -1)."""
    return replace(scenario, segments=tuple(replace(s, angle_deg=abs(s.angle_deg) * sense) if s.kind == "turn"
                                            else s for s in scenario.segments))


def wait_until(condition, what: str = "the condition", timeout: float = 5.0) -> None:
    """Polls `condition` until it holds; fails naming `what` after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.005)


def plug(link: Path) -> tuple[int, int]:
    """A new raw pty behind `link` (master and slave fds), as udev (re-)creates /dev/stim300 when
    the adapter is plugged in."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    tmp = link.with_suffix(".new")
    tmp.symlink_to(os.ttyname(slave))
    os.replace(tmp, link)
    return master, slave


class Terminal(io.StringIO):
    """A text stream that says it is a terminal."""

    def isatty(self):
        return True


def command_env(**variables: str) -> dict[str, str]:
    """The environment of this tree's commands run as subprocesses: they import this tree, see none
    of the systemd variables the tests themselves may run with (a daemon would notify the test
    runner's service manager), and see `variables`."""
    return {**{k: v for k, v in os.environ.items() if k not in SYSTEMD_ENV}, **variables, "PYTHONPATH": str(ROOT)}


def calibd(*args: str, env: dict[str, str] | None = None, **options) -> subprocess.Popen:
    """`calibd ARGS` as a subprocess, its stdout and stderr piped unless `options` say otherwise;
    `env` adds variables to command_env()."""
    return subprocess.Popen([sys.executable, "-m", "calibd.cli", *map(str, args)], cwd=ROOT,
                            env=command_env(**(env or {})),
                            **{"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, **options})
