"""Live cost of the daemon: `calibd run` fed at 2000 Hz in real time through a pty.

Targets (daemon issue): <= 5% of one core, memory flat over a 10-minute run (the daemon collects
and re-solves every minute from the second minute on; RSS is printed per minute), and `calibd
calibrate` on the 125 Hz thesis fixture in <= 2 s wall. Baselines measured in the same run: a
bare pyserial reader on the same stream (what reading alone costs), and `stim300 info` on the
fixture (what decoding alone costs).

    python benchmarks/live.py [--seconds 600] [--write-bytes 4096]

`--write-bytes` is how the stream reaches the pty: 4096-byte writes (a burst every 35 ms at
2000 Hz, so the reader wakes about 30 times a second), or small ones such as 64 (bytes arriving
all the time, as from a UART or a USB adapter: the reader then wakes every `batch_s`).
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
import tty
from dataclasses import replace
from pathlib import Path

from calibd.scenario import Segment, load_scenario
from calibd.sim import capture_bytes, simulate

ROOT = Path(__file__).resolve().parents[1]
WARMUP_WINDOW_S = 60  # the simulated sensor is warm: the daemon collects and solves from the 2nd minute on
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
BARE_READER = ("import serial, sys, time\n"
               "s = serial.Serial(sys.argv[1], 921600, timeout=0.05)\n"
               "end = time.monotonic() + float(sys.argv[2])\n"
               "while time.monotonic() < end:\n"
               "    s.read(max(1, s.in_waiting)); time.sleep(0.004)\n")


def cpu_seconds(pid: int, thread: int | None = None) -> float:
    """CPU time (user + system, s) of process `pid`, or of its thread `thread` alone."""
    stat = Path(f"/proc/{pid}/stat" if thread is None else f"/proc/{pid}/task/{thread}/stat")
    fields = stat.read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def usage(pid: int) -> tuple[float, float, float, float]:
    """(wall s, CPU s, RSS MB, main thread's CPU s): the rest of the CPU is the port reader thread's."""
    return time.monotonic(), cpu_seconds(pid), rss_mb(pid), cpu_seconds(pid, pid)


def capture_2000hz(seconds: float) -> tuple[bytes, float]:
    """A 2000 Hz stream `seconds` long (30 s static, then a 90 deg turn and a static every minute,
    the last static to the end) and its duration in data time (s), which the feed paces by."""
    base = load_scenario("thesis-real")
    turns = max(0, int((seconds - 30) // 60))
    segments = [Segment("static", duration_s=30 + (seconds - 30) * (turns == 0))]
    for k in range(turns):  # a 5.5 s turn and 54.5 s static make a minute
        rest_s = seconds - 30 - 60 * turns if k == turns - 1 else 0.0
        segments += [Segment("turn", angle_deg=90, peak_rate_deg_s=20, accel_deg_s2=20),
                     Segment("static", duration_s=54.5 + rest_s)]
    scenario = replace(base, sensor=replace(base.sensor, sample_rate_hz=2000), segments=tuple(segments))
    sim = simulate(scenario)
    data, _ = capture_bytes(sim)
    return data, float(sim.time_s[-1] - sim.time_s[0]) + 1 / 2000


def feed(master: int, data: bytes, rate_bytes_s: float, write_bytes: int, process, samples: list) -> None:
    """Write `data` paced in real time, `write_bytes` at a time; every 10 s record (wall, cpu, rss,
    main thread's cpu) of `process`."""
    start = time.monotonic()
    next_sample = start
    for offset in range(0, len(data), write_bytes):
        time.sleep(max(0.0, start + offset / rate_bytes_s - time.monotonic()))
        view = memoryview(data)[offset:offset + write_bytes]
        while view:
            if select.select([], [master], [], 1.0)[1]:
                view = view[os.write(master, view):]
        if time.monotonic() >= next_sample:
            samples.append(usage(process.pid))
            next_sample += 10.0


def measure(command: list[str], data: bytes, seconds: float, write_bytes: int) -> list:
    """Run `command` on a pty fed `data` over `seconds` (its data time: real time)."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    path = os.ttyname(slave)
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "calibd.toml"
        config.write_text(f'[serial]\nport = "{path}"\n[site]\nlatitude_deg = 40.59129\n'
                          f'[output]\nstate_dir = "{tmp}/state"\n[warmup]\nwindow_s = {WARMUP_WINDOW_S}\n')
        argv = [a.replace("{port}", path).replace("{config}", str(config)).replace("{seconds}", str(seconds + 5))
                for a in command]
        process = subprocess.Popen(argv, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(2.0)  # imports, port open
        samples = []
        try:
            feed(master, data, len(data) / seconds, write_bytes, process, samples)
            samples.append(usage(process.pid))
        finally:
            process.send_signal(signal.SIGTERM)
            process.wait(timeout=30)
            os.close(master)
            os.close(slave)
    return samples


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="real-time feed length (default 600 s)")
    ap.add_argument("--write-bytes", type=int, default=4096, help="bytes per write into the pty (default 4096)")
    args = ap.parse_args()
    data, seconds = capture_2000hz(args.seconds)
    print(f"2000 Hz 0xA7 stream, {seconds:.0f} s, {len(data) / 1e6:.1f} MB, fed in real time through a pty "
          f"{args.write_bytes} bytes a write")
    runs = {"bare pyserial reader": [sys.executable, "-c", BARE_READER, "{port}", "{seconds}"],
            "calibd run": [sys.executable, "-m", "calibd.cli", "run", "--config", "{config}"]}
    cpu = {}
    for name, command in runs.items():
        samples = measure(command, data, seconds, args.write_bytes)
        (t0, c0, m0, main0), (t1, c1, m1, main1) = samples[0], samples[-1]
        cpu[name] = 100 * (c1 - c0) / (t1 - t0)
        main = 100 * (main1 - main0) / (t1 - t0)
        print(f"{name}: {cpu[name]:.2f}% of one core (main thread {main:.2f}%, other threads "
              f"{cpu[name] - main:.2f}%: in calibd run, the port reader); RSS {m0:.0f} MB -> {m1:.0f} MB "
              f"(max {max(s[2] for s in samples):.0f} MB); load average {os.getloadavg()[0]:.2f} (1 min)")
        minutes = [max(s[2] for s in samples if t0 + 60 * k <= s[0] < t0 + 60 * (k + 1))
                   for k in range(int((t1 - t0) // 60))]
        print(f"  RSS max per minute: {' '.join(f'{m:.0f}' for m in minutes)} MB")
    print(f"calibd run / bare reader CPU: {cpu['calibd run'] / max(cpu['bare pyserial reader'], 0.01):.1f}x "
          f"(target: calibd run <= 5% of one core, its port reader thread <= 1%)")
    fixture = ROOT / "fixtures" / "thesis_real_cw_125hz.bin"
    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, command in (("stim300 info", [sys.executable, "-m", "stim300.cli", "info", str(fixture)]),
                              ("calibd calibrate", [sys.executable, "-m", "calibd.cli", "calibrate", str(fixture),
                                                    "--latitude", "40.59129", "-o", f"{tmp}/r.json"])):
            runs = []
            for _ in range(3):  # best of 3: the first run after the feed meets cold caches
                t = time.perf_counter()
                subprocess.run(command, env=ENV, check=True, stdout=subprocess.DEVNULL)
                runs.append(time.perf_counter() - t)
            times[name] = min(runs)
    print(f"calibd calibrate on the 125 Hz thesis fixture: {times['calibd calibrate']:.2f} s wall, best of 3 "
          f"(target <= 2 s); stim300 info on it {times['stim300 info']:.2f} s; ratio "
          f"{times['calibd calibrate'] / times['stim300 info']:.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
