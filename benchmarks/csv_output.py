"""CSV output: the shared writer `stim300.csvtable.write_rows` against np.savetxt, which both CSV
outputs used before, on the same columns of a simulated 2000 Hz capture.

Target (CSV issue): the rows of `stim300 decode -o OUT.csv` and of `calibd apply -o OUT.csv`
written >= 3x faster than np.savetxt, byte for byte the same. Both ways are measured in this
run on the same columns, written to memory (the formatting, not the disk), best CPU time of
--repeat runs; the whole commands on the shipped fixture are timed for information.

(Not named csv.py: run as a script, this folder comes first on sys.path and would hide the
standard library's csv module, which importlib.metadata imports.)

    python benchmarks/csv_output.py [--seconds 180] [--repeat 3]
"""

from __future__ import annotations

import argparse
import io
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from calibd.apply import TIME_FORMAT, VALUE_FORMAT, UNITS, Correction, CsvWriter, apply_capture
from live import capture_2000hz
from stim300.bulk import decode_columns
from stim300.cli import _write_csv, columns, sample_times

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
FIXTURE = ROOT / "fixtures" / "heading137_lat60_125hz.bin"
DECODE_CHUNK = 100_000  # rows per np.savetxt call, as `stim300 decode` wrote them


def savetxt_rows(out, blocks: list[list[np.ndarray]], formats: list[str]) -> None:
    """The baseline: each block stacked into float64 and written by np.savetxt, as both outputs did."""
    for block in blocks:
        np.savetxt(out, np.column_stack(block).astype(np.float64, copy=False), fmt=formats, delimiter=",")


def apply_blocks(data: bytes) -> list[dict[str, np.ndarray]]:
    """The corrected column blocks `calibd apply` hands its writer, in the decoder's block sizes."""
    blocks = []
    biases = Correction({cluster: np.full(3, 1e-4) for cluster in UNITS})
    apply_capture(data, "sim", biases, None, False, lambda block: blocks.append(
        {name: values.copy() for name, values in block.items()}))
    return blocks


def best_cpu_s(write, repeat: int) -> tuple[float, bytes]:
    """Best process CPU time (s) of `repeat` runs of `write(out)`, and what it wrote."""
    times = []
    for _ in range(repeat):
        out = io.BytesIO()
        started = time.process_time()
        write(out)
        times.append(time.process_time() - started)
    return min(times), out.getvalue()


def rows_after(text: bytes, header_lines: int) -> bytes:
    return text.split(b"\n", header_lines)[header_lines]


def compare(name: str, rows: int, baseline, new, header_lines: int, repeat: int) -> None:
    old_s, old = best_cpu_s(baseline, repeat)
    new_s, text = best_cpu_s(new, repeat)
    same = rows_after(text, header_lines) == old
    print(f"{name}: {rows} rows, {len(old) / 1e6:.1f} MB; np.savetxt {old_s:.2f} s, csvtable {new_s:.2f} s CPU "
          f"({rows / new_s / 1e6:.2f} M rows/s): {old_s / new_s:.1f}x (target >= 3x); bytes identical: "
          f"{'yes' if same else 'NO'}")


def command_s(argv: list[str]) -> tuple[float, float]:
    """(wall s, CPU s) of one run of a command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    subprocess.run(argv, env=ENV, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.perf_counter() - started, after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=180.0, help="simulated 2000 Hz capture length (default 180 s)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each writer, the best counted (default 3)")
    args = ap.parse_args()
    print(f"load average at start: {' '.join(f'{x:.2f}' for x in os.getloadavg())} (2-core machine)")
    data, seconds = capture_2000hz(args.seconds)
    print(f"2000 Hz 0xA7 capture, {seconds:.0f} s, {len(data) / 1e6:.1f} MB")

    samples, info = decode_columns(data)
    cols = columns(samples, sample_times(samples, info).time_s)
    names = list(cols)
    formats = ["%d" if cols[n].dtype.kind in "ui" else "%.6f" if n in ("t_s", "t_host_s") else "%.9g" for n in names]
    rows = len(cols[names[0]])
    chunks = [[cols[n][start:start + DECODE_CHUNK] for n in names] for start in range(0, rows, DECODE_CHUNK)]
    compare("stim300 decode -o OUT.csv", rows, lambda out: savetxt_rows(out, chunks, formats),
            lambda out: _write_csv(out, cols), 1, args.repeat)

    blocks = apply_blocks(data)
    clusters = [c for c in UNITS if f"{c}_{UNITS[c]}" in blocks[0]]
    tables = [[b["time_s"], *(b[f"{c}_{UNITS[c]}"] for c in clusters), b["counter"], b["status"], b["power_up"]]
              for b in blocks]
    apply_formats = [TIME_FORMAT, *[VALUE_FORMAT] * 3 * len(clusters), *["%d"] * 5]

    def write_apply(out):
        writer = CsvWriter(out, {"capture": "sim"})
        for block in blocks:
            writer(block)

    compare("calibd apply -o OUT.csv", sum(len(b["time_s"]) for b in blocks),
            lambda out: savetxt_rows(out, tables, apply_formats), write_apply, 3, args.repeat)

    with tempfile.TemporaryDirectory() as tmp:
        python = sys.executable
        command_s([python, "-m", "calibd.cli", "calibrate", str(FIXTURE), "--latitude", "60", "-o", f"{tmp}/r.json"])
        commands = {"stim300 decode": [python, "-m", "stim300.cli", "decode", str(FIXTURE), "-o", f"{tmp}/d.csv"],
                    "calibd apply": [python, "-m", "calibd.cli", "apply", f"{tmp}/r.json", str(FIXTURE),
                                     "-o", f"{tmp}/a.csv"]}
        for name, argv in commands.items():
            wall, cpu = min(command_s(argv) for _ in range(args.repeat))
            print(f"{name} {FIXTURE.name} -o x.csv (whole command, for information): {wall:.2f} s wall, "
                  f"{cpu:.2f} s CPU, best of {args.repeat}")
    print(f"load average at end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
