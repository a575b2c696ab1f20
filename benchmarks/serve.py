"""What serving costs: `calibd run` bare against `calibd run` serving, side by side in one run,
each fed the same 2000 Hz stream in real time through a pty.

Serving: 4 socket clients watching samples (2 raw, 2 corrected), one client that watches raw
samples and never reads, two raw ptys each with its own reader, the corrected pty with a reader
that behaves like a driver (asks `C` once, then writes a request the pty refuses every 100 ms),
the "best" correction policy, and, halfway through, 1000 connect/disconnect cycles and 10 MB of
garbage commands. Printed: the daemon's CPU (% of one core, and the ratio to bare), its RSS over
time, the reading clients' sample latency (host read -> socket, from each sample's t_host), the
bytes each pty reader got against the bytes fed, the served run's log lines by event, and how far
the served run's result lies from the bare run's (in sigma).
Targets: CPU <= 2x bare and <= 8 % of a core; latency p99 < 50 ms; RSS flat; every raw reader
gets every byte; the served run's log under 100 lines for 10 minutes; result unchanged.

With --feeds the second run publishes ROS 2 topics and the Foxglove view instead ([ros2] and
[foxglove]; DDS on loopback), with a ROS 2 subscriber of both Imu topics in a process of its own
(benchmarks/ros2_listen.py) and a Foxglove client watching every channel. Printed beside the
CPU: the share of samples each Imu topic delivered (target >= 99.9 %), whether they came in
order with strictly increasing stamps, the stamps' jitter against the sensor's clock (each 10 s
of stamps against a straight line through them; target <= 50 us RMS), whether every corrected
sample is its raw twin through a published result's correction (biases out, then the factory
terms it estimated) and how often the correction taken changed, and the Foxglove messages per channel.

    python benchmarks/serve.py [--seconds 600] [--quick] [--feeds]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tty
from collections import Counter
from pathlib import Path

import numpy as np

from live import ENV, ROOT, capture_2000hz, feed, usage  # benchmarks/live.py: the stream and its real-time feed
from ros2_publish import LOOPBACK  # DDS on loopback only, unicast discovery

from calibd.correction import ServedCorrection, si_biases, through
from calibd.results import parse_result


WARMUP_WINDOW_S = 60
GARBAGE_BYTES = 10_000_000
CYCLES = 1000


class Watcher(threading.Thread):
    """A socket client watching samples of `kind`, keeping each sample's latency (s)."""

    def __init__(self, path: Path, kind: str):
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(str(path))
        self.sock.sendall(f'?WATCH={{"enable":true,"samples":"{kind}"}};\n'.encode())
        self.latency_s: list[float] = []
        self.newest_latency_s: list[float] = []
        self.samples = 0
        self.overflows = 0

    def run(self) -> None:
        reader = self.sock.makefile("rb")
        for line in reader:
            now = time.monotonic()
            message = json.loads(line)
            if message["class"] == "SAMPLES":
                t_host = np.asarray(message["t_host"])
                self.latency_s.extend((now - t_host).tolist())
                self.newest_latency_s.append(now - t_host.max())
                self.samples += len(t_host)
            elif message["class"] == "OVERFLOW":
                self.overflows += 1


class PtyReader(threading.Thread):
    """Reads a served pty to its end, counting bytes; a `pester`ing reader also asks `C` once and
    then writes a request the pty refuses every 100 ms, as a confused driver would."""

    def __init__(self, link: Path, pester: bool = False):
        super().__init__(daemon=True)
        self.fd = os.open(link, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        self.bytes = 0
        self.requests = 0
        if pester:
            threading.Thread(target=self._pester, daemon=True).start()

    def run(self) -> None:
        try:
            while chunk := os.read(self.fd, 65536):
                self.bytes += len(chunk)
        except OSError:
            pass

    def _pester(self) -> None:
        try:
            os.write(self.fd, b"C\r")
            while True:
                time.sleep(0.1)
                os.write(self.fd, b"Q\r")  # not a request the corrected pty answers
                self.requests += 1
        except OSError:
            pass


def abuse(path: Path) -> None:
    """1000 connect/disconnect cycles, then 10 MB of garbage commands on one connection."""
    for _ in range(CYCLES):
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.connect(str(path))
    line = b"?GARBAGE=" + b"x" * 990 + b";\n"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.connect(str(path))
        sock.setblocking(False)
        sent = 0
        while sent < GARBAGE_BYTES:
            try:
                sent += sock.send(line * 100)
            except BlockingIOError:
                time.sleep(0.001)
            try:
                sock.recv(1 << 20)  # the ERRORs, so the server's queue for us is not what limits
            except BlockingIOError:
                pass


class FoxgloveCounter(threading.Thread):
    """A Foxglove WebSocket client subscribed to every channel the view advertises, counting the
    messages of each (the view does no work for a channel nobody watches)."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        from websockets.sync.client import connect

        deadline = time.monotonic() + 30
        while True:
            try:
                self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5)
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self.counts: Counter = Counter()
        self.topics: dict[int, str] = {}

    def run(self) -> None:
        try:
            for frame in self.ws:
                if isinstance(frame, bytes):
                    self.counts[self.topics[int.from_bytes(frame[1:5], "little")]] += 1
                    continue
                message = json.loads(frame)
                if message["op"] == "advertise":
                    new = {len(self.topics) + i: c for i, c in enumerate(message["channels"])}
                    self.topics |= {i: c["topic"] for i, c in new.items()}
                    self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": i, "channelId": c["id"]} for i, c in new.items()]}))
        except Exception:  # the daemon stopped
            return


def ros2_figures(path: Path, rate_hz: float) -> str:
    """What the ROS 2 subscriber got (benchmarks/ros2_listen.py's NPZ), in words."""
    got = np.load(path)
    lines = []
    for kind in ("raw", "corrected"):
        stamps = got[f"{kind}_stamp_ns"]
        if len(stamps) < 2:
            lines.append(f"{kind}: {len(stamps)} samples")
            continue
        steps = np.diff(stamps) * rate_hz / 1e9
        expected = int(np.rint(steps).sum()) + 1  # from its first to its last sample
        t = (stamps - stamps[0]) / 1e9
        residual = []
        for lo in range(0, len(t), int(10 * rate_hz)):  # each 10 s against its own straight line
            part = t[lo:lo + int(10 * rate_hz)]
            if len(part) > 10:
                index = np.concatenate([[0], np.cumsum(np.rint(np.diff(part) * rate_hz))])
                residual.append(part - np.polyval(np.polyfit(index, part, 1), index))
        jitter_us = 1e6 * np.sqrt(np.mean(np.concatenate(residual) ** 2))
        lines.append(f"imu/{'data_raw' if kind == 'raw' else 'data'}: {len(stamps):,} samples of the "
                     f"{expected:,} from its first to its last ({100 * len(stamps) / expected:.3f} %, target >= "
                     f"99.9 %), stamps {'strictly increasing' if np.all(steps > 0) else 'NOT in order'}, "
                     f"jitter {jitter_us:.1f} us RMS (target <= 50 us)")
    lines.append(corrected_figures(got))
    return "\n".join(lines)


def corrected_figures(got) -> str:
    """Whether each corrected sample is its raw twin through one of the published results'
    corrections (biases out, then the factory terms it estimated, as docs/ros2.md says), and how
    often the one taken changed."""
    raw = {s: i for i, s in enumerate(got["raw_stamp_ns"].tolist())}
    pairs = [(raw[s], i) for i, s in enumerate(got["corrected_stamp_ns"].tolist()) if s in raw]
    if not pairs:
        return "corrected: no sample with a raw twin"
    raw_values = got["raw_values"][[r for r, _ in pairs]]
    corrected = got["corrected_values"][[c for _, c in pairs]]
    results = [parse_result(document, "imu/calibration") for document in got["documents"].tolist()]
    taken = np.full(len(pairs), -1)
    for index, result in enumerate(results):
        correction = ServedCorrection.of(result)
        if correction is None:
            continue
        bias = si_biases(result)
        predicted = np.hstack([through(raw_values[:, 3 * k:3 * k + 3] - bias.get(block, 0.0),
                                       correction.maps.get(block)) for k, block in enumerate(("gyro", "acc"))])
        match = np.all(np.abs(predicted - corrected) <= 1e-9 * np.abs(raw_values) + 1e-12, axis=1)
        taken[(taken < 0) & match] = index
    changes = int(np.count_nonzero(np.diff(taken[taken >= 0])))
    return (f"corrected = raw through a published result's correction: {np.count_nonzero(taken >= 0):,} of "
            f"{len(pairs):,} pairs ({len(results)} results published), the correction taken changed {changes} "
            f"times, constant between")


def event_name(line: str) -> str:
    """The event of one log line (JSON or console rendering), or the line's first word."""
    try:
        return json.loads(line)["event"]
    except (ValueError, KeyError, TypeError):
        words = line.split()
        return next((w for w in words if w.isidentifier()), line[:20])


def measure(data: bytes, seconds: float, serve: bool, feeds: bool = False) -> dict:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    with tempfile.TemporaryDirectory() as tmp:
        sock_path = Path(tmp) / "calibd.sock"
        table = f'[serve]\nsocket = "{sock_path}"\n' if serve else ""
        if serve:
            table += (f'raw_pty = ["{tmp}/raw1", "{tmp}/raw2"]\ncorrected_pty = "{tmp}/corrected"\n'
                      'correction = "best"\n')
        listener, fox = None, None
        if feeds:
            domain, fox_port = random.randint(1, 200), free_port()
            table += f'[serve]\ncorrection = "best"\n[ros2]\ndomain_id = {domain}\n[foxglove]\nport = {fox_port}\n'
            listener = subprocess.Popen([sys.executable, str(ROOT / "benchmarks" / "ros2_listen.py"), str(domain),
                                         f"{tmp}/ros2.npz"], env={**ENV, "CYCLONEDDS_URI": LOOPBACK},
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            assert listener.stdout.readline() == "ready\n"
        config = Path(tmp) / "calibd.toml"
        config.write_text(f'[serial]\nport = "{os.ttyname(slave)}"\n[site]\nlatitude_deg = 40.59129\n'
                          f'[output]\nstate_dir = "{tmp}/state"\n[warmup]\nwindow_s = {WARMUP_WINDOW_S}\n{table}')
        log = open(Path(tmp) / "stderr", "w+")
        process = subprocess.Popen([sys.executable, "-m", "calibd.cli", "run", "--config", str(config)],
                                   env={**ENV, "CYCLONEDDS_URI": LOOPBACK}, stdout=subprocess.DEVNULL, stderr=log)
        time.sleep(2.0)  # imports, port open, socket bound
        if feeds:
            fox = FoxgloveCounter(fox_port)
            fox.start()
        while serve and not sock_path.exists():
            if process.poll() is not None:
                log.seek(0)
                raise SystemExit(f"calibd run failed: {log.read()[-2000:]}")
            time.sleep(0.1)
        clients, readers, stalled = [], [], None
        if serve:
            clients = [Watcher(sock_path, kind) for kind in ("raw", "raw", "corrected", "corrected")]
            stalled = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            stalled.connect(str(sock_path))
            stalled.sendall(b'?WATCH={"enable":true,"samples":"raw"};\n')  # and never reads again
            readers = [PtyReader(Path(tmp) / name, name == "corrected") for name in ("raw1", "raw2", "corrected")]
            for thread in (*clients, *readers):
                thread.start()
            threading.Timer(seconds / 2, abuse, (sock_path,)).start()
        samples = []
        try:
            feed(master, data, len(data) / seconds, process, samples)
            time.sleep(1.0)
            samples.append(usage(process.pid))
        finally:
            process.send_signal(signal.SIGTERM)
            process.wait(timeout=30)
            os.close(master)
            os.close(slave)
            log.seek(0)
            log_lines = log.read().splitlines()
            log.close()
            if stalled is not None:
                stalled.close()
        ros2 = None
        if listener is not None:
            listener.communicate("stop\n", timeout=120)
            ros2 = ros2_figures(Path(tmp) / "ros2.npz", 2000)
        result_file = Path(tmp) / "state" / "result.json"
        result = json.loads(result_file.read_text()) if result_file.exists() else None
    return {"usage": samples, "clients": clients, "readers": readers, "result": result, "log": log_lines,
            "ros2": ros2, "foxglove": None if fox is None else dict(fox.counts)}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="real-time feed length of each run (default 600 s)")
    ap.add_argument("--quick", action="store_true", help="150 s runs")
    ap.add_argument("--feeds", action="store_true", help="the second run publishes ROS 2 and Foxglove instead")
    args = ap.parse_args()
    seconds_asked = 150.0 if args.quick else args.seconds
    data, seconds = capture_2000hz(seconds_asked)
    print(f"2000 Hz stream, {seconds:.0f} s, {len(data) / 1e6:.1f} MB, fed in real time through a pty to each run; "
          f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())} on {os.cpu_count()} cores")
    if args.feeds:
        return feeds_main(data, seconds)
    runs = {name: measure(data, seconds, serve) for name, serve in (("bare", False), ("serving", True))}
    cpu, steady = {}, {}
    for name, run in runs.items():
        usage_ = run["usage"]
        (t0, c0, _, _), (t1, c1, _, _) = usage_[0], usage_[-1]
        half = max((u for u in usage_ if u[0] <= t0 + seconds / 2), key=lambda u: u[0])  # before the abuse
        cpu[name] = 100 * (c1 - c0) / (t1 - t0)
        steady[name] = 100 * (half[1] - c0) / max(half[0] - t0, 1e-6)
        rss = " ".join(f"{u[2]:.0f}" for u in usage_)
        print(f"{name}: daemon CPU {steady[name]:.2f} % of one core over the first half (serving: before the "
              f"connect storm and the garbage), {cpu[name]:.2f} % over the whole run; RSS every 10 s: {rss} MB")
    for what, figures in (("first half", steady), ("whole run", cpu)):
        ratio = figures["serving"] / max(figures["bare"], 1e-6)
        print(f"serving / bare CPU, {what}: {ratio:.2f}x, serving {figures['serving']:.2f} % of a core (targets: "
              f"<= 2x and <= 8 %: {'met' if ratio <= 2 and figures['serving'] <= 8 else 'NOT met'})")
    clients = runs["serving"]["clients"]
    latency_ms = 1000 * np.concatenate([c.latency_s for c in clients])
    newest_ms = 1000 * np.concatenate([c.newest_latency_s for c in clients])
    print(f"reading clients (one other stalled): {', '.join(str(c.samples) for c in clients)} samples, "
          f"{sum(c.overflows for c in clients)} OVERFLOW; latency read -> socket per sample p50 "
          f"{np.percentile(latency_ms, 50):.1f} ms, p99 {np.percentile(latency_ms, 99):.1f} ms, max "
          f"{latency_ms.max():.1f} ms (target p99 < 50 ms); newest sample of each batch p99 "
          f"{np.percentile(newest_ms, 99):.1f} ms")
    raw1, raw2, corrected = runs["serving"]["readers"]
    for reader, name in ((raw1, "raw pty 1"), (raw2, "raw pty 2")):
        print(f"{name} reader: {reader.bytes:,} of the {len(data):,} bytes fed "
              f"({'every byte' if reader.bytes == len(data) else f'{len(data) - reader.bytes:,} short'})")
    print(f"corrected pty reader: {corrected.bytes / 1e6:.1f} MB, {corrected.requests} refused requests written")
    log = runs["serving"]["log"]
    events = Counter(event_name(line) for line in log)
    print(f"served run's log: {len(log)} lines in {seconds:.0f} s (target for 600 s: < 100): "
          + ", ".join(f"{name} {count}" for name, count in events.most_common()))
    bare, served = runs["bare"]["result"], runs["serving"]["result"]
    if bare is None or served is None:
        print("no result in one of the runs: the result comparison needs a longer run")
    else:
        shifts = [abs(served["estimates"][k]["value"] - e["value"]) / e["sigma"]
                  for k, e in bare["estimates"].items() if e.get("sigma")]
        print(f"result with serving (and {CYCLES} connect/disconnect cycles, {GARBAGE_BYTES / 1e6:.0f} MB of garbage) "
              f"against bare: largest estimate difference {max(shifts):.3f} sigma")
    return 0


def feeds_main(data: bytes, seconds: float) -> int:
    """Bare against ROS 2 and Foxglove on."""
    runs = {"bare": measure(data, seconds, False), "feeds": measure(data, seconds, False, feeds=True)}
    cpu = {}
    for name, run in runs.items():
        (t0, c0, _, _), (t1, c1, _, _) = run["usage"][0], run["usage"][-1]
        cpu[name] = 100 * (c1 - c0) / (t1 - t0)
        print(f"{name}: daemon CPU {cpu[name]:.2f} % of one core; RSS every 10 s: "
              + " ".join(f"{u[2]:.0f}" for u in run["usage"]) + " MB")
    ratio = cpu["feeds"] / max(cpu["bare"], 1e-6)
    print(f"ROS 2 and Foxglove on / bare CPU: {ratio:.2f}x (target <= 2x: {'met' if ratio <= 2 else 'NOT met'}); "
          f"load average now {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(runs["feeds"]["ros2"])
    print("Foxglove messages: " + ", ".join(f"{topic} {n}" for topic, n in sorted(runs["feeds"]["foxglove"].items())))
    log = runs["feeds"]["log"]
    print(f"log: {len(log)} lines: " + ", ".join(f"{n} {c}" for n, c in Counter(map(event_name, log)).most_common()))
    bare, fed = runs["bare"]["result"], runs["feeds"]["result"]
    if bare and fed:
        shifts = [abs(fed["estimates"][k]["value"] - e["value"]) / e["sigma"]
                  for k, e in bare["estimates"].items() if e.get("sigma")]
        print(f"result with ROS 2 and Foxglove against bare: largest estimate difference {max(shifts):.3f} sigma")
    return 0


if __name__ == "__main__":
    sys.exit(main())
