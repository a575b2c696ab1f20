"""Fuzzing every reader of a document or a line from outside: mutated copies of real documents
must each be read or refused with calibd's one-line error, never raise anything else, and never
take long.

The readers, as the programs use them:

- `command`: the socket server's command parser (a line a client sends);
- `message`: `calibd.client`'s reading of a server line (what `calibd watch` and `pipe` take);
- `result`: a result.json (`apply`, `report`, `status`, the daemon at start);
- `state`: a state.json as `calibd status` reads it;
- `noise`: a `calibd noise` file (`plan --noise`);
- `config`: a daemon configuration (TOML);
- `scenario`: a simulation scenario (TOML).

Seeds are made in this run (a calibration and a replay of a shipped capture, its noise figures,
the shipped configuration and scenarios); each input is one seed with one to four mutations: a
JSON or TOML value replaced by a hostile one (deep nesting, NaN, infinities, 1e308, a 5000-digit
integer, a value of another type, a long string), a key removed or added, bytes flipped, inserted
or cut. Prints, per reader, the inputs, how many were read and refused, the exceptions that were
not calibd's own (target: 0) and the slowest input.

    python benchmarks/fuzz_documents.py [--count 100000 | --minutes 60] [--seed 0] [--workers 2]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CAPTURE = ROOT / "fixtures" / "heading137_lat60_125hz.bin"
HOSTILE_JSON = ("[" * 5000 + "]" * 5000, "NaN", "Infinity", "-Infinity", "1e308", "-1e308", "1e999", "9" * 5000,
                "\"x\"", "\"\"", "[]", "{}", "null", "true", "-1", "0", "\"" + "a" * 100_000 + "\"", "[1,2,3]",
                "{\"x\":[{\"y\":null}]}", "4.9e-324")
HOSTILE_TOML = ("[" * 5000 + "]" * 5000, "nan", "inf", "-inf", "1e308", "-1e308", "9" * 5000, "\"x\"", "[]",
                "{}", "true", "-1", "0", "1979-05-27T07:32:00Z", "\"" + "a" * 100_000 + "\"", "{ a = { b = 1 } }")
COMMANDS = (b"?POLL;", b"?DEVICE;", b"?VERSION;", b'?WATCH={"enable":true,"samples":"raw"};',
            b'?WATCH={"enable":false};')


def make_seeds(work: Path) -> dict[str, list[bytes]]:
    """Real documents of each kind, made by the project's own commands in `work`."""
    calibd = [sys.executable, "-m", "calibd"]
    result, noise, state_dir = work / "result.json", work / "noise.json", work / "state"
    subprocess.run([*calibd, "calibrate", str(CAPTURE), "--latitude", "60", "-o", str(result)],
                   check=True, capture_output=True)
    subprocess.run([*calibd, "noise", str(CAPTURE), "-o", str(noise)], check=True, capture_output=True)
    subprocess.run([*calibd, "replay", str(CAPTURE), "--latitude", "60", "--state-dir", str(state_dir)],
                   check=True, capture_output=True)
    sys.path.insert(0, str(ROOT))
    from calibd.serve.protocol import Poll, Result, State, StateFields, Version, encode
    doc = json.loads(result.read_bytes())
    state = json.loads((state_dir / "state.json").read_bytes())
    messages = [encode(m) for m in (Version.this(), Result(doc), State("COLLECTING", "statics 2 of 3", {"statics": 2}),
                                    Poll(StateFields(state["state"], state["detail"]), doc))]
    return {"command": list(COMMANDS), "message": messages, "result": [result.read_bytes()],
            "state": [(state_dir / "state.json").read_bytes()], "noise": [noise.read_bytes()],
            "config": [(ROOT / "systemd" / "calibd.example.toml").read_bytes()],
            "scenario": [p.read_bytes() for p in sorted((ROOT / "calibd" / "scenarios").glob("*.toml"))]}


def readers(work: Path):
    """reader name -> a function of the input's bytes that reads it as the programs do."""
    from calibd.documents import load_state
    from calibd.client import message_of
    from calibd.config import load_config
    from calibd.planner import noise_from_json
    from calibd.results import parse_result
    from calibd.scenario import load_scenario
    from calibd.serve.protocol import decode, parse_command

    def through_file(read, name: str):
        path = work / name

        def run(data: bytes):
            path.write_bytes(data)
            return read(path)
        return run
    return {"command": parse_command, "message": lambda data: message_of(decode(data)),
            "result": lambda data: parse_result(data, "result.json"),
            "state": through_file(load_state, "state.json"),
            "noise": lambda data: noise_from_json(data, "noise.json"),
            "config": through_file(load_config, "calibd.toml"),
            "scenario": through_file(lambda p: load_scenario(str(p)), "scenario.toml")}


def mutate(rng: np.random.Generator, seed: bytes, toml: bool) -> bytes:
    """One to four mutations of `seed`: a value replaced by a hostile one, bytes flipped, cut or
    inserted (a structural mutation first when the seed is JSON)."""
    data = seed
    for _ in range(int(rng.integers(1, 5))):
        kind = rng.integers(4)
        if kind == 0 or kind == 1:
            data = _replace_value(rng, data, HOSTILE_TOML if toml else HOSTILE_JSON, toml)
        elif kind == 2 and data:
            buf = bytearray(data)
            for at in rng.integers(0, len(buf), int(rng.integers(1, 9))):
                buf[at] = int(rng.integers(256))
            data = bytes(buf)
        elif data:
            at = int(rng.integers(len(data)))
            data = data[:at] + rng.integers(0, 256, int(rng.integers(0, 16)), dtype=np.uint8).tobytes() \
                + data[at + int(rng.integers(0, 64)):]
    return data


def _replace_value(rng: np.random.Generator, data: bytes, hostile: tuple[str, ...], toml: bool) -> bytes:
    """A value of the document (after a ':' in JSON, a '=' in TOML) replaced by a hostile one, or
    a line removed (TOML) / a key renamed (JSON)."""
    mark = b"=" if toml else b":"
    places = [i for i in range(len(data)) if data[i:i + 1] == mark]
    if not places:
        return data
    at = places[int(rng.integers(len(places)))] + 1
    end = _value_end(data, at, toml)
    if rng.random() < 0.1:  # drop the whole entry: a key missing
        start = data.rfind(b"\n" if toml else b",", 0, at) + 1
        return data[:start] + data[end + (not toml):]
    return data[:at] + hostile[int(rng.integers(len(hostile)))].encode() + data[end:]


def _value_end(data: bytes, at: int, toml: bool) -> int:
    """Where the value starting at `at` ends: its line's end (TOML), or the ',' or closing bracket
    that ends it at its own depth (JSON; strings skipped)."""
    if toml:
        end = data.find(b"\n", at)
        return len(data) if end < 0 else end
    depth, i, in_string = 0, at, False
    while i < len(data):
        c = data[i:i + 1]
        if in_string:
            if c == b"\\":
                i += 1
            elif c == b'"':
                in_string = False
        elif c == b'"':
            in_string = True
        elif c in b"[{":
            depth += 1
        elif c in b"]}":
            if depth == 0:
                return i
            depth -= 1
        elif c == b"," and depth == 0:
            return i
        i += 1
    return i


def fuzz_range(seed: int, start: int, stop: int, seeds: dict[str, list[bytes]]) -> dict:
    """Inputs start..stop-1, round-robin over the readers: per reader (inputs, read, refused,
    foreign exceptions, slowest s, the first foreign exception)."""
    from calibd.errors import CalibdError
    from stim300.errors import Stim300Error
    with tempfile.TemporaryDirectory() as tmp:
        read = readers(Path(tmp))
        names = sorted(read)
        tally = {name: [0, 0, 0, 0, 0.0, None] for name in names}
        for k in range(start, stop):
            rng = np.random.default_rng([seed, k])
            name = names[k % len(names)]
            choices = seeds[name]
            data = mutate(rng, choices[int(rng.integers(len(choices)))], name in ("config", "scenario"))
            row = tally[name]
            row[0] += 1
            t = time.perf_counter()
            try:
                read[name](data)
                row[1] += 1
            except (CalibdError, Stim300Error):
                row[2] += 1
            except Exception as exc:  # noqa: BLE001 - counting them is the point
                row[3] += 1
                if row[5] is None:
                    row[5] = f"input {k} (seed [{seed}, {k}]): {type(exc).__name__}: {str(exc)[:200]}"
            row[4] = max(row[4], time.perf_counter() - t)
    return tally


CHUNK = 5000  # inputs a worker takes at a time (progress is printed per chunk)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=100_000, help="inputs over all readers (default 100000)")
    ap.add_argument("--minutes", type=float, help="run this long instead, whatever the count")
    ap.add_argument("--seed", type=int, default=0, help="seed of the mutations (default 0)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes (default: one per core)")
    args = ap.parse_args()
    return run(args.count, args.seed, args.workers, args.minutes)


def run(count: int, seed: int, workers: int, minutes: float | None = None) -> int:
    """Fuzz `count` inputs (or as many as `minutes` allow) over the readers in `workers`
    processes, print the tally; 1 when any reader raised something else than calibd's own errors."""
    t = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        seeds = make_seeds(Path(tmp))
    print(f"seeds made in {time.perf_counter() - t:.1f} s: "
          + ", ".join(f"{name} {len(docs)}" for name, docs in seeds.items()), flush=True)
    t = time.perf_counter()
    deadline = None if minutes is None else t + 60 * minutes
    total: dict[str, list] = {}
    done = 0
    with ProcessPoolExecutor(workers) as pool:
        starts = iter(range(0, 1 << 62 if deadline else count, CHUNK))
        running = [pool.submit(fuzz_range, seed, a, a + CHUNK if deadline else min(a + CHUNK, count), seeds)
                   for a in itertools.islice(starts, 2 * workers)]
        while running:
            tally = running.pop(0).result()
            for name, row in tally.items():
                into = total.setdefault(name, [0, 0, 0, 0, 0.0, None])
                into[:4] = [a + b for a, b in zip(into[:4], row[:4])]
                into[4] = max(into[4], row[4])
                into[5] = into[5] or row[5]
            done += sum(row[0] for row in tally.values())
            print(f"  {done} inputs, {time.perf_counter() - t:.0f} s, "
                  f"{sum(row[3] for row in total.values())} other exceptions", flush=True)
            a = next(starts, None)
            if a is not None and (deadline is None or time.perf_counter() < deadline):
                running.append(pool.submit(fuzz_range, seed, a, a + CHUNK if deadline else min(a + CHUNK, count),
                                           seeds))
    elapsed = time.perf_counter() - t
    print(f"documents: {done} inputs in {elapsed:.0f} s ({done / elapsed:.0f} a second)")
    for name, (n, accepted, refused, foreign, slowest, first) in sorted(total.items()):
        print(f"  {name:9s} {n:8d} inputs: {accepted:7d} read, {refused:7d} refused, {foreign} other exceptions, "
              f"slowest {slowest * 1e3:.1f} ms")
        if first:
            print(f"            first: {first}")
    return 1 if any(row[3] for row in total.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
