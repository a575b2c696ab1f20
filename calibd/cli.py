"""`calibd simulate`: make a capture with known truth from a scenario.

Errors in files, scenarios or arguments end with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
import time

from stim300.cliutil import CommandParser, UsageError, run_command

from .scenario import READY_MADE, ScenarioError, load_scenario
from .sim import write_capture


def cmd_simulate(args) -> int:
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as exc:
        raise UsageError(str(exc)) from None
    started = time.perf_counter()
    try:
        record = write_capture(scenario, args.output)
    except OSError as exc:
        raise UsageError(f"{args.output}: cannot write: {(exc.strerror or str(exc)).lower()}") from None
    print(f"{scenario.name}: {record['samples']} samples, {record['duration_s']:.1f} s at "
          f"{scenario.sensor.sample_rate_hz} Hz -> {args.output} (+ .truth.json) in "
          f"{time.perf_counter() - started:.1f} s", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(prog="calibd", description="STIM300 calibration: simulated sessions with known truth.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=CommandParser)
    p = sub.add_parser("simulate", help="scenario -> capture file and CAPTURE.truth.json")
    p.add_argument("scenario", help=f"scenario TOML file, or one of: {', '.join(READY_MADE)}")
    p.add_argument("-o", "--output", required=True, help="capture file to write")
    p.set_defaults(func=cmd_simulate)
    return parser


def main(argv=None) -> int:
    return run_command(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
