"""`calibd run | replay | status | calibrate | batch | sensitivity | plan | noise | report | apply |
simulate | pipe | watch | trim`: the daemon, its pipeline on a capture, its state; one-shot calibration
and many captures at once on Dask; what alpha/beta errors cost; what a campaign will give before it
is run; the noise of a capture; a report people can look at; a result applied to a capture; captures
with known truth; the daemon's socket as JSON lines and as a live view; the sensor's bias trim.

Errors in files, scenarios or arguments end with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import select
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from stim300.cliutil import (DOCUMENT_LIMIT_BYTES, CommandParser, RunError, input_file, not_an_input, path_arg,
                             read_input, run_command, write_error)
from stim300.errors import UsageError

from . import spec
from .captures import capture_bytes, first_stream_info, is_imu_recording, load_session, open_capture
from .errors import CalibdError, CalibrationError
from .frames import STANDARD_GRAVITY, Site, site_value_error
from .scenarios import READY_MADE
from .serve import SAMPLE_KINDS
from .units import DEG, estimate_rows

if TYPE_CHECKING:
    from .config import ServeConfig
    from .results import CalibrationResult

# Each command imports what only it needs in its own body (the daemon, the methods and scipy, matplotlib), so
# that a command pays for its own imports only (docs/architecture.md, Start-up; benchmarks/startup.py).


def cmd_simulate(args) -> int:
    from .scenario import ScenarioError, load_scenario

    for output in (args.output, f"{args.output}.truth.json"):  # refused before anything is written
        not_an_input(output, args.scenario)
        if os.path.isdir(output):
            raise UsageError(f"{output}: cannot write: is a directory")
    scenario = load_scenario(args.scenario)
    from .sim import write_capture  # the simulator (and scipy.signal) only when simulating

    started = time.perf_counter()
    try:
        record = write_capture(scenario, args.output)
    except ScenarioError as exc:  # what only the simulation finds: its size, faults it cannot apply
        raise UsageError(f"{args.scenario}: {exc}") from None
    except OSError as exc:
        raise write_error(args.output, exc) from None
    print(f"{scenario.name}: {record['samples']} samples, {record['duration_s']:.1f} s at "
          f"{scenario.sensor.sample_rate_hz} Hz -> {args.output} (+ .truth.json) in "
          f"{time.perf_counter() - started:.1f} s", file=sys.stderr)
    return 0


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def _number(low: float, high: float, unit: str):
    def parse(text: str) -> float:
        value = _float(text)
        if not (low <= value <= high):
            raise argparse.ArgumentTypeError(f"{text} is outside [{low:g}, {high:g}] {unit}")
        return value
    return parse


PLATFORM_RATE_DEG_S = (0.1, spec.GYRO_RANGE_DEG_S)  # |rate|: a full turn within an hour, within the gyros' range


def _magnitude(low: float, high: float, unit: str):
    """A signed option whose magnitude is in [low, high] (a rate of 0 turns nothing)."""
    def parse(text: str) -> float:
        value = _float(text)
        if not (low <= abs(value) <= high):
            raise argparse.ArgumentTypeError(f"{text} is outside +-[{low:g}, {high:g}] {unit}")
        return value
    return parse


def _positive_int(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive whole number")
    return int(text)


def _site_value(field: str):
    """An option's parser for the Site's `field`: the Site's own range and words."""
    def parse(text: str) -> float:
        value = _float(text)
        reason = site_value_error(field, value)
        if reason is not None:
            raise argparse.ArgumentTypeError(reason)
        return value
    return parse


def _add_site_options(p: argparse.ArgumentParser, required: bool, optional_when: str = "without --config") -> None:
    p.add_argument("--latitude", type=_site_value("latitude_deg"), required=required,
                   help="site latitude, deg" + ("" if required else f" ({optional_when})"))
    p.add_argument("--height", type=_site_value("height_m"), default=0.0, help="site height, m (default 0)")
    p.add_argument("--g0", type=_site_value("g0"), help="measured gravity, m/s^2 (default: normal gravity)")


def _site(args) -> Site:
    return Site(args.latitude, args.height, args.g0)


def _summary(result: CalibrationResult) -> str:
    source = result.stream.capture  # a result of an older version, or a foreign one, may not say
    lines = [f"{result.method}: {source}" if source else result.method, f"  site: {_site_line(result.site)}"]
    session = _session_line(result)
    if session:
        lines.append(f"  session: {session}")
    lines += [f"  {row}" for row in estimate_rows(result.estimates)]
    lines += [f"  warning: {w}" for w in result.warnings]
    return "\n".join(lines)


def _site_line(site: dict) -> str:
    """The site a result used: a wrong-sign latitude moves the gyro Z bias by 2 Omega_E sin|lat|."""
    given = site.get("g0_given")
    source = "" if given is None else " (given)" if given else " (normal gravity)"
    return (f"latitude {site['latitude_deg']:+.5f} deg, height {site.get('height_m', 0.0):g} m, "
            f"g0 {site.get('g0_m_s2', STANDARD_GRAVITY):.5f} m/s^2{source}")


def _session_line(result: CalibrationResult) -> str | None:
    """Which power-up (calibrate) or daemon session the result rests on, and its time span."""
    stream = result.stream
    power_up = stream.power_up
    if power_up:
        span = f"{stream.start_s or 0.0:.1f} s to {power_up.duration_s:.1f} s of it"
        return f"power-up {power_up.number} of {power_up.count}, {span}, from {stream.start_by or 'given'}"
    session = result.session
    if session:
        return f"session {session.number} since the daemon started, {session.duration_s:.1f} s of data"
    return None


def _method_settings(args, command: str) -> tuple[str, dict]:
    """The method and its options `calibrate` and `batch` were given, checked together."""
    if (args.alpha is None) != (args.beta is None):
        raise UsageError(f"{command}: give both --alpha and --beta (the nominal run) or neither (the linear run)")
    if args.bench and args.alpha is not None:
        raise UsageError(f"{command}: --bench estimates alpha and beta itself; drop --alpha/--beta")
    if args.method == "joint" and (args.alpha is not None or args.platform_rate is not None or args.bench):
        raise UsageError(f"{command}: --alpha/--beta, --platform-rate and --bench belong to --method thesis; the "
                         "joint method estimates alpha and beta itself")
    if args.method == "thesis" and (args.fixed_amplitude or args.drift or args.index_step is not None):
        raise UsageError(f"{command}: --fixed-amplitude, --index-step and --drift belong to --method joint")
    for flag, given in (("--remounted", getattr(args, "remounted", None)),
                        ("--intrinsics", getattr(args, "intrinsics", None))):
        if given is not None and (args.method != "joint" or args.bench):
            raise UsageError(f"{command}: {flag} belongs to --method joint")
    options = {"fixed_amplitude": args.fixed_amplitude, "drift": args.drift, "alpha_deg": args.alpha,
               "beta_deg": args.beta, "platform_rate_deg_s": args.platform_rate, **_index_settings(args, command),
               "intrinsics": getattr(args, "intrinsics", None)}
    return "thesis-bench" if args.bench else args.method, options


def cmd_calibrate(args) -> int:
    from .calibrate import calibrate_capture
    from .methods import OptionError, estimator
    from .results import write_result

    name, settings = _method_settings(args, "calibrate")
    site = _site(args)
    not_an_input(args.output, args.capture)
    capture = open_capture(args.capture, topic=args.topic)  # a refusal names the capture

    method = estimator(name)
    _not_the_capture(args, capture)
    try:
        options = method.options(settings)
    except OptionError as exc:
        raise UsageError(f"calibrate: {exc.reason}") from None
    second = _second_mounting(args, capture, site, options)

    def solve(session):
        if second is not None:
            from .methods.joint import joint_real_case
            return joint_real_case(session, site, options, None, second)
        return method.solve(session, site, None, options)

    try:
        result = calibrate_capture(capture, solve, args.power_up, args.start)
    except CalibrationError as exc:
        raise UsageError(f"{args.capture}: {exc}") from None
    try:
        write_result(args.output, result)
    except OSError as exc:
        raise write_error(args.output, exc) from None
    print(_summary(result))
    return 0


def _not_the_capture(args, capture) -> None:
    """An --intrinsics result that rests on the capture being calibrated is refused: its terms
    would count this data twice (the results among themselves: `methods.joint.intrinsics`)."""
    from .results import load_result

    for path in args.intrinsics or ():
        not_an_input(args.output, path)
        if (load_result(path).session_id or "").split("/")[0] == capture.identity["sha256"][:16]:
            raise UsageError(f"{path}: rests on the same data as the capture calibrated: its terms would be counted "
                             "twice")


def _remount_sigma(args, command: str) -> float | None:
    """The second mounting's fixture 1-sigma, rad, from --remount-sigma (its default with
    --remounted); None without a second mounting (`_add_remount_options`)."""
    from .methods.base import DEFAULT_REMOUNT_SIGMA_DEG

    if not args.remounted:
        if args.remount_sigma is not None:
            raise UsageError(f"{command}: --remount-sigma is the second mounting's 1-sigma: give --remounted too")
        return None
    return (DEFAULT_REMOUNT_SIGMA_DEG if args.remount_sigma is None else args.remount_sigma) * DEG


def _second_mounting(args, capture, site: Site, options):
    """The unit's second mounting `--remounted` names (calibd.calibrate.second_mounting); None without one."""
    sigma = _remount_sigma(args, "calibrate")
    if sigma is None:
        return None
    from .calibrate import second_mounting

    not_an_input(args.output, args.remounted)
    other = open_capture(args.remounted, topic=args.topic)
    try:
        return second_mounting(capture, other, site, options, sigma)
    except CalibrationError as exc:
        raise UsageError(f"{args.remounted}: {exc}") from None


def cmd_batch(args) -> int:
    import signal

    from .batch import BatchSettings, run_batch
    from .engine import cluster
    from .fleettable import pyarrow
    from .methods import estimator

    name, settings = _method_settings(args, "batch")
    if args.scheduler is not None and args.workers is not None:
        raise UsageError("batch: --workers sizes the local cluster; a cluster given by --scheduler has its own workers")
    for given in args.captures:
        not_an_input(args.output, given)
    estimator(name).options(settings)  # refused here, not once per capture
    pyarrow()  # the table's writer, before a cluster is started
    batch = BatchSettings(name, _site(args), settings, args.start, args.topic)

    def stop(signum, frame):
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, stop)  # like Ctrl-C: the finished rows are folded into the table first
    try:
        with cluster(args.scheduler, args.workers) as client:
            tally = run_batch(args.captures, batch, args.output, client, redo=args.redo)
    except KeyboardInterrupt:
        print(f"batch: stopped; the captures done are in {args.output}, run the same command again for the rest",
              file=sys.stderr)
        return 130
    print(f"{args.output}: {tally.done} captures done ({tally.power_ups} power-ups calibrated, {tally.refused} "
          f"refused; {tally.failed} captures failed, {tally.duplicates} duplicates), {tally.skipped} already in the "
          "table")
    return 0


def cmd_fleet(args) -> int:
    """The fleet report: the text on stdout, and the HTML page when --html names a file (docs/fleet.md)."""
    from stim300.atomic import write_atomic

    from .fleet import analyse, text_report
    from .fleettable import read_rows

    if args.html is not None:
        not_an_input(args.html, args.table)
        if Path(args.html).is_dir():
            raise UsageError(f"{args.html}: is a directory, expected an HTML file name")
    fleet = analyse(args.table, read_rows(args.table), args.serial)
    page = None
    if args.html is not None:
        from .fleetfigures import render_html

        page = render_html(fleet)  # drawn before the text is printed: a missing matplotlib says so first
    print(text_report(fleet), end="")
    if page is not None:
        try:
            write_atomic(args.html, page.encode())
        except OSError as exc:
            raise write_error(args.html, exc) from None
    return 0


def cmd_sensitivity(args) -> int:
    from .estimators.thesis import sensitivity

    site = _site(args)
    s = sensitivity(args.alpha_error * DEG, args.beta_error * DEG, args.platform_rate * DEG, site)
    print(f"interface-tilt errors d_alpha {args.alpha_error:g} deg, d_beta {args.beta_error:g} deg at a platform "
          f"rate of {args.platform_rate:g} deg/s, latitude {site.latitude_deg:g} deg (docs/thesis-estimators.md, "
          "sensitivity to interface-tilt errors):")
    print(f"  inclinometer X bias error  {s['incl_bias_x'] / STANDARD_GRAVITY * 1000:.4f} mg  (g0 sin d_beta)")
    print(f"  gyro Y bias error          {s['gyro_bias_y'] / DEG * 3600:.3f} deg/h  (rate x d_alpha)")
    print(f"  yaw error                  {s['yaw'] / DEG:.2f} deg  (gyro Y error / Omega_E cos(lat))")
    return 0


def _load_config(path: str, port: str | None):
    """The configuration at `path`, its port replaced by `port` when given; ConfigError if unusable."""
    from .config import load_config

    config = load_config(path)
    return config.with_port(port) if port else config


def _config(path: str, port: str | None):

    return _load_config(path, port)


def cmd_run(args) -> int:
    from .live import configure_logging, run

    config = _config(args.config, args.port)
    configure_logging()
    _drop_log_event("start_failed")  # run says why in its one stderr line (the journal keeps it too)
    return run(config, lambda: _load_config(args.config, args.port))  # a bad reload keeps the old one


def _replay_serve(args, config) -> ServeConfig | None:
    """What `replay --serve` serves: the [serve] table of --config, with --socket, --raw-pty and
    --corrected-pty (which imply --serve) in place of its keys; None without serving. A replay
    serves only when told (a run's configuration may name the real daemon's socket), and says
    so when --config has a [serve] table, so that nothing being served is no surprise."""
    from .config import ServeConfig

    given = {key: Path(value) for key, value in (("socket", args.socket), ("raw_pty", args.raw_pty),
                                                 ("corrected_pty", args.corrected_pty)) if value is not None}
    if not (args.serve or given):
        if config and config.serving:
            print(f"calibd replay: {args.config} serves the sensor ({', '.join(config.served_tables)}): a replay "
                  "serves only with --serve", file=sys.stderr)
        return None
    serve = replace(config.serve if config else ServeConfig(), **given)
    if not (serve.serving or (config and config.serving)):
        raise UsageError("replay --serve: nothing to serve: give --socket, --raw-pty or --corrected-pty, or a "
                         "[serve], [ros2], [foxglove] or [record] table in --config")
    return serve


NO_WARM_UP_CHECK = ("no temperatures: the warm-up cannot be checked, and the first message is not the sensor's "
                    "power-up; calibration starts at the first message, as calibrate's does (--warmup-window S "
                    "waits S s of data first)")


def cmd_replay(args) -> int:
    import contextlib
    import logging

    from stim300.progress import Progress
    from stim300.source import CaptureSource, PtySource

    from .config import DetectionConfig, MethodConfig, ServeConfig, WarmupConfig
    from .daemon import Calibrator, Callbacks, StateLog
    from .live import configure_logging, replay
    from .recordingbytes import recording_bytes
    from .statedir import ResultStore
    from .serve.hub import Hub, make_feeds
    from .warmup import WINDOW_RANGE_S
    from .serve.sockets import ServeError

    config = _config(args.config, None) if args.config else None
    mcap = None if args.mcap is None else Path(args.mcap)
    if mcap is not None:
        if mcap.suffix != ".mcap":
            raise UsageError(f"--mcap {args.mcap}: name it .mcap (the Foxglove view's channels, docs/foxglove.md)")
        not_an_input(args.mcap, args.capture)
    if config:
        site, warmup, method, detection = config.site, config.warmup, config.method, config.detection
    elif args.latitude is not None:
        site, warmup, method, detection = _site(args), WarmupConfig(), MethodConfig(), DetectionConfig()
    else:
        raise UsageError("replay: give --config FILE or --latitude DEG")
    serve = _replay_serve(args, config)
    if args.warmup_window is not None:
        warmup = replace(warmup, window_s=args.warmup_window)
    origin = None
    if is_imu_recording(args.capture):  # Imu messages: the datagrams they stand for
        replayed = recording_bytes(args.capture, args.topic)
        origin = replayed.origin
        data, reads = replayed.data, replayed.reads
        warnings = replayed.warnings
        if args.warmup_window is None:  # its first message is no power-up: as calibrate, from the first message
            warmup = replace(warmup, window_s=WINDOW_RANGE_S[0], min_time_s=0.0)
            warnings = [*warnings, NO_WARM_UP_CHECK]
        for line in (replayed.description(), *(f"warning: {w}" for w in warnings)):
            print(f"calibd replay: {args.capture}: {line}", file=sys.stderr)
    else:
        with capture_bytes(args.capture, args.topic) as (data, reads, _):  # a file, or the MCAP stim300 record writes
            data = bytes(data)  # held whole: the replay paces it out
        _refuse_without_datagrams(data, args.capture)
    bar = Progress("replay", len(data), "B")
    out = bar.above(sys.stdout)  # a state line printed while the bar is drawn goes above it
    last = [None]

    def print_state(state, detail):
        if state != last[0] or detail.startswith("solved"):
            print(f"[{state.value}] {detail}", file=out, flush=True)
            last[0] = state

    def print_stale(result):
        print(f"[{result.stale.power_up} power-up] {result.stale.reason}", file=out, flush=True)

    listeners = [StateLog(), Callbacks(state=print_state, stale=print_stale)]
    store = None
    if args.state_dir:  # a capture is a world of its own: an earlier result there is not shown
        store = ResultStore(args.state_dir, {"capture": args.capture})
        listeners.append(store)
    configure_logging(logging.WARNING)
    _drop_log_event("state_dir_error")  # a state directory that fails is the run's one error line, at its end
    speed_text = args.speed or ("1" if serve else "max")  # served: as a sensor sends, unless told
    speed = None if speed_text == "max" else float(speed_text)
    hub = None
    if serve or mcap:
        served = config if serve and config else None
        try:
            feeds = make_feeds(served and served.ros2, served and served.foxglove, mcap)
            hub = Hub(serve or ServeConfig(), args.capture, feeds=feeds, paced=speed == 1,
                      record=served and served.record)
        except ServeError as exc:  # as for the daemon: serving that cannot start fails the run
            raise RunError(str(exc)) from None
        listeners.append(hub)
    calibrator = Calibrator(site, warmup, method, listeners, source=args.capture, detection=detection, origin=origin)
    try:
        source = PtySource(data, speed, tap=hub and hub.tap) if args.pty or hub \
            else CaptureSource(data, speed, reads=reads)
    except BaseException:
        if hub is not None:
            hub.close()
        raise
    with bar, contextlib.redirect_stderr(bar.above(sys.stderr)):  # and so does a log line
        replay(source, calibrator, progress=lambda done, total: bar.update(done), hub=hub)
    if store is not None:
        store.retry()
        if store.degraded:
            raise RunError(f"state directory {args.state_dir}: {store.degraded}")
    if calibrator.result is None or calibrator.result.stale is not None:
        stale = " (the last result is the previous power-up's, marked stale)" if calibrator.result else ""
        raise RunError(f"{args.capture}: no result for the last power-up{stale}: {calibrator.detail}")
    print(_summary(calibrator.result))
    return 0


class _Found(CalibdError):
    """A datagram was decoded: the scan for one can stop (never leaves `_refuse_without_datagrams`)."""


def _refuse_without_datagrams(data, path: str) -> None:
    """Refuse (exit 2), as calibrate and `stim300 info` do, a capture in which no STIM300 datagram
    is found: scanned at numpy speed (300 MB in about a second) up to the first one, where the
    daemon's pipeline would take minutes to find nothing."""
    from stim300.bulk import decode_blocks

    def found(samples, scanner, offset):
        raise _Found

    try:
        decode_blocks(data, found)
    except _Found:
        return
    raise UsageError(f"{path}: no STIM300 datagram found (not a STIM300 capture)")


def _drop_log_event(event: str) -> None:
    """Keep the log lines named `event` off stderr: what the command says itself, in its one line."""
    import structlog

    def drop(logger, method, fields):
        if fields.get("event") == event:
            raise structlog.DropEvent
        return fields

    structlog.configure(processors=[drop, *structlog.get_config()["processors"]])


def _status(directory: Path, as_json: bool, one_line: bool = False) -> str:
    """What `calibd status` prints for the state directory: the state and the last result in
    words, or (`as_json`) the object {"state": state.json as written, "result": result.json's
    document or null}, what ?POLL gives on the daemon's socket (`one_line`: one JSON line).
    UsageError (one line) for a directory without a state.json or a file that is not calibd's."""
    from .results import parse_result
    from .documents import load_state

    state_file, result_file = directory / "state.json", directory / "result.json"
    if not os.path.lexists(state_file):  # Path.exists raises where the directory cannot be read
        raise UsageError(f"{directory}: no state.json (is calibd running with this state directory?)")
    state = load_state(state_file)
    # a state directory's files are the daemon's: a symbolic link there is refused, not followed
    result = parse_result(read_input(result_file, "result file", DOCUMENT_LIMIT_BYTES, follow=False),
                          result_file) if os.path.lexists(result_file) else None
    if as_json:
        document = {"state": state, "result": None if result is None else result.to_dict()}
        return json.dumps(document) if one_line else json.dumps(document, indent=1)
    lines = [f"state: {state['state']} ({state['detail']}), updated {time.time() - state['updated']:.0f} s ago"]
    lines += [f"{key.replace('_', ' ')}: {state[key]}" for key in ("degraded", "held_back")
              if isinstance(state.get(key), str)]
    if result is None:
        return "\n".join(lines + ["no result yet"])
    if result.stale is not None:
        lines.append(f"result: stale since {result.stale.since}, from the {result.stale.power_up} power-up")
    return "\n".join(lines + [_summary(result)])


def cmd_status(args) -> int:
    directory = Path(args.state_dir)
    if args.follow:
        return _client_program(lambda: _follow_status(directory, args.json))
    print(_status(directory, args.json))
    return 0


STATUS_POLL_S = 0.5  # how often --follow looks at the state directory's files


def _file_stamp(path: Path) -> tuple[int, int, int] | None:
    """What changes when a file is replaced (atomically: a new inode) or rewritten: its inode,
    size and modification time (ns); None while it is absent or cannot be looked at."""
    try:
        stat = os.lstat(path)
    except OSError:
        return None
    return stat.st_ino, stat.st_size, stat.st_mtime_ns


def _follow_status(directory: Path, as_json: bool) -> int:
    """`calibd status --follow`: the status, then again each time state.json or result.json
    changes (a block of lines, or one JSON line each). A state directory that goes away or holds
    a file calibd cannot read is said once on stderr and waited for (a daemon's runtime directory
    goes with the daemon and comes back when it starts again); only the first look refuses."""
    files = (directory / "state.json", directory / "result.json")
    seen, said = None, None
    while True:
        stamps = [_file_stamp(path) for path in files]
        if stamps != seen:
            try:
                text = _status(directory, as_json, one_line=True)
            except UsageError as exc:
                if seen is None:
                    raise
                if str(exc) != said:
                    print(f"calibd: {exc}; waiting for it to change", file=sys.stderr, flush=True)
                    said = str(exc)
            else:
                print(text if as_json or seen is None else f"\n{text}", flush=True)
                said = None
            seen = stamps
        _wait_unless_stdout_closed(STATUS_POLL_S)


def _wait_unless_stdout_closed(seconds: float) -> None:
    """Wait `seconds`, or end at once (BrokenPipeError, as a write would) when the reader of
    stdout has gone: with nothing new to print, `status --follow | head -n 1` would otherwise
    never end. poll() says POLLERR or POLLHUP for a pipe or socket whose reader closed, nothing
    for a file or a terminal."""
    poller = select.poll()
    poller.register(sys.stdout.fileno(), 0)  # no events asked for: errors and hang-ups come anyway
    if poller.poll(seconds * 1000):
        raise BrokenPipeError(errno.EPIPE, "the reader of stdout has gone")


def cmd_report(args) -> int:
    from .report import figures_dir, write_report  # matplotlib only for this command

    input_file(args.result, "result file")
    not_an_input(args.output, args.result, args.capture)
    topic = args.topic
    if topic is None and is_imu_recording(args.capture):  # the topic the result was made from
        from .results import parse_result

        topic = parse_result(read_input(args.result, "result file", DOCUMENT_LIMIT_BYTES), args.result).stream.topic
    try:
        written = write_report(args.result, open_capture(args.capture, topic=topic), args.output, svg=args.svg)
    except OSError as exc:
        raise write_error(args.output, exc) from None
    figures = (f"figures: {', '.join(p.name for p in written[1:])} in {figures_dir(written[0])}/" if written[1:]
               else "figures in the page only (no directory beside a device or FIFO)")
    print(f"report: {written[0]}; {figures}")
    return 0


PLAN_NOISE_OPTIONS = {  # calibd plan option -> (calibd.spec.NoiseFigures field, unit, what)
    "--arw": ("gyro_arw_deg_sqrt_h", "deg/sqrt(h)", "gyro angle random walk"),
    "--bias-instability": ("gyro_bias_instability_deg_h", "deg/h", "gyro bias instability"),
    "--vrw": ("acc_vrw_m_s_sqrt_h", "m/s/sqrt(h)", "accelerometer velocity random walk"),
    "--acc-bias-instability": ("acc_bias_instability_mg", "mg", "accelerometer bias instability"),
    "--incl-vrw": ("incl_vrw_m_s_sqrt_h", "m/s/sqrt(h)", "inclinometer velocity random walk"),
    "--incl-bias-instability": ("incl_bias_instability_mg", "mg", "inclinometer bias instability"),
}


def cmd_plan(args) -> int:
    from .planner import (builtin_campaign, campaign_from_scenario, noise_from_json,  # the simulator
                          report, time_to_target)  # only here
    from .scenario import load_scenario

    given = {field: getattr(args, field) for field, _, _ in PLAN_NOISE_OPTIONS.values()
             if getattr(args, field) is not None}
    if args.noise and given:
        raise UsageError("plan: give --noise FILE or noise figures (--arw, ...), not both")
    if args.latitude is None and (args.campaign or args.g0 is not None or args.height):
        raise UsageError("plan: --latitude is needed with --campaign, --height or --g0 (a scenario file has its own "
                         "[site], which --latitude replaces)")
    if args.scenario:
        campaign = campaign_from_scenario(load_scenario(args.scenario), args.scenario)
    else:
        campaign = builtin_campaign(args.campaign)
    site = campaign.scenario.site if args.latitude is None else _site(args)
    figures = (noise_from_json(read_input(args.noise, "noise file", DOCUMENT_LIMIT_BYTES), args.noise)
               if args.noise else replace(campaign.figures, **given))
    from .methods import OptionError, estimator

    try:
        options = estimator("joint").options(_index_settings(args, "plan") | {"intrinsics": args.intrinsics})
    except OptionError as exc:
        raise UsageError(f"plan: {exc.reason}") from None
    reach = time_to_target(campaign, site, figures, args.target_yaw_deg * DEG, options=options,
                           remount_sigma=_remount_sigma(args, "plan"))
    print(report(reach, figures))
    return 0


def _ros_topic(text: str) -> str:
    """A ROS graph name (letters, digits, _ and /, not starting with a digit): written unquoted into YAML."""
    name = text.lstrip("/")
    if not name or name[0].isdigit() or not all(c.isascii() and (c.isalnum() or c in "_/") for c in name):
        raise argparse.ArgumentTypeError(f"{text!r} is not a ROS topic name (letters, digits, _ and /)")
    return text


def cmd_noise(args) -> int:
    from stim300.atomic import write_atomic

    from .noise import NoiseError, characterise, kalibr_yaml, noise_record, noise_table

    for output in (args.output, args.kalibr):
        if output:
            not_an_input(output, args.capture)
    if args.output and args.output == args.kalibr:
        raise UsageError(f"noise: -o and --kalibr name the same file {args.output}")
    try:
        session = load_session(args.capture, args.start, topic=args.topic)
    except CalibrationError as exc:  # a decoding refusal names the capture, a power-up's does not
        text = str(exc)
        raise UsageError(text if text.startswith(f"{args.capture}:") else f"{args.capture}: {text}") from None
    try:
        channels = characterise(session)
    except NoiseError as exc:
        raise UsageError(f"{args.capture}: {exc}") from None
    rostopic = args.rostopic or session.stream.topic or "/imu0"  # a recording's own topic by default
    documents = [(args.output, lambda: json.dumps(noise_record(session, channels, args.capture), indent=1) + "\n"),
                 (args.kalibr, lambda: kalibr_yaml(session, channels, rostopic))]
    for output, document in documents:
        if output:
            try:
                write_atomic(output, document().encode())
            except OSError as exc:
                raise write_error(output, exc) from None
    print(f"{args.capture}: {noise_table(channels)}")
    return 0


APPLY_OUTPUTS = (".npz", ".csv", ".mcap")
MCAP_FRAME_IDS = {"imu": "imu_link", "home": "imu_home"}  # the Imu messages' frame_id by apply's frame


def cmd_apply(args) -> int:
    """A result's biases taken off a capture's samples, in SI, into NPZ, CSV or MCAP (docs/apply.md)."""
    import hashlib

    from stim300.atomic import atomic_file
    from stim300.cliutil import package_version

    from .apply import ApplyError, correction, meta_record
    from .results import parse_result

    kind = Path(args.output).suffix.lower()
    if kind not in APPLY_OUTPUTS:
        raise UsageError(f"apply: {args.output}: unknown output type {kind or '(no extension)'!r}: "
                         f"name it .npz, .csv or .mcap")
    not_an_input(args.output, args.result, args.capture)
    result_bytes = read_input(args.result, "result file", DOCUMENT_LIMIT_BYTES)
    try:
        result = parse_result(result_bytes, args.result)  # the bytes hashed into the output's meta
        fix = correction(result, args.frame, args.force)
    except ApplyError as exc:
        raise UsageError(f"{args.result}: {exc}") from None
    meta = meta_record(fix, args.result, hashlib.sha256(result_bytes).hexdigest(), result, args.capture,
                       package_version())
    try:
        with atomic_file(args.output, durable=False) as f:
            applied = _apply_into(f, kind, args, fix, meta, result, result_bytes)
    except OSError as exc:
        raise write_error(args.output, exc) from None
    for text in applied.warnings:
        print(f"calibd apply: warning: {text}", file=sys.stderr)
    frame = "the home frame (NWU at the platform's home position)" if args.frame else "IMU axes"
    print(f"{args.capture}: {applied.words}, biases of {args.result} subtracted, in SI units (rad/s, m/s^2) in "
          f"{frame} -> {args.output}")
    return 0


def _apply_into(f, kind: str, args, fix, meta: dict, result, result_bytes: bytes):
    """apply's writing into the open output `f`: a STIM300 capture (decoded block by block, its
    pages let go), or a recording of Imu messages (batch by batch); the writer of `kind` is
    made once the stream's rate is known, and finished."""
    from stim300.protocol import INTERNAL_RATE_HZ

    from .apply import CsvWriter, NpzWriter, apply_capture, apply_recording
    from .recordings import ImuRecording

    writers = []

    def open_writer(rate_hz: float, acc_range_g: int | None, capacity: int, frame_id: str):
        if kind == ".mcap":
            writers.append(_mcap_writer(f, meta, result, result_bytes, rate_hz, acc_range_g, frame_id))
        else:
            writers.append(NpzWriter(capacity, f, meta) if kind == ".npz" else CsvWriter(f, meta))
        return writers[-1]

    if is_imu_recording(args.capture):
        recording = ImuRecording(args.capture, args.topic, preferred=result.stream.topic)
        applied = apply_recording(recording, fix, result, args.force, lambda rate_hz, frame_id: open_writer(
            rate_hz, None, recording.messages, frame_id if fix.frame == "imu" else MCAP_FRAME_IDS["home"]))
    else:
        with capture_bytes(args.capture, args.topic) as (data, reads, let_go):
            info = first_stream_info(data)
            writer = open_writer(info.rate_hz or INTERNAL_RATE_HZ, info.sensor_record().acc_range_g,
                                 NpzWriter.capacity_for(len(data)), MCAP_FRAME_IDS[fix.frame])
            applied = apply_capture(data, args.capture, fix, result.sensor.serial_number, args.force, writer, reads,
                                    let_go)
    for writer in writers:
        writer.finish()
    return applied


def _mcap_writer(f, meta: dict, result, result_bytes: bytes, rate_hz: float, acc_range_g: int | None, frame_id: str):
    """apply's MCAP writer, its noise covariances at the stream's rate and range (None: not known)."""
    from .correction import noise_covariances
    from .mcapout import McapImuWriter

    return McapImuWriter(f, meta, result, result_bytes, noise_covariances(rate_hz, acc_range_g), frame_id)


def _client_program(body) -> int:
    """`body()` of a program reading the daemon's socket: its failures one line (exit 1); Ctrl-C
    and a reader of stdout that went away (`| head`) end it quietly (exit 0, no traceback)."""
    from .client import ClientError
    from .serve.protocol import ProtocolError
    try:
        return body()
    except (ClientError, ProtocolError) as exc:
        raise RunError(str(exc)) from None
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


def _token(path: str | None) -> str | None:
    """The token in a --token-file (the daemon's [serve] tcp_token_file); None without one."""
    from .serve.protocol import MAX_TOKEN_BYTES, ProtocolError, token_of

    if path is None:
        return None
    try:
        return token_of(read_input(path, "token file", MAX_TOKEN_BYTES + 64))
    except ProtocolError as exc:
        raise UsageError(f"{path}: {exc}") from None


def cmd_pipe(args) -> int:
    """Every message of the daemon's socket on stdout as it was sent, one a line (gpspipe -w), or
    with --bytes the sensor's bytes alone (gpspipe -R)."""
    from .client import Client

    def pipe() -> int:
        out = sys.stdout.buffer
        if args.bytes and (args.samples != "none" or args.raw):
            raise UsageError("pipe: --bytes writes the sensor's bytes alone: drop --samples and --raw")
        with Client.connect(args.socket, token=_token(args.token_file)) as client:
            if args.bytes:
                return _pipe_bytes(client, out, args.count)
            client.command("WATCH", {"enable": True, "samples": args.samples} | ({"raw": True} if args.raw else {}))
            line, written = client.version_line, 0
            while True:
                out.write(line + b"\n")
                out.flush()
                written += 1
                if written == args.count:
                    return 0
                line = client.read_line()
    return _client_program(pipe)


def _pipe_bytes(client, out, count: int | None) -> int:
    """The sensor's bytes from the RAW messages, as read, on `out` (a capture `stim300 info`
    reads); a gap (bytes this client lost while it did not keep up) is said on stderr, once per gap."""
    from .client import Raw

    client.watch(raw=True)
    written, expected = 0, None
    while count is None or written < count:
        message = client.read()
        if not isinstance(message, Raw):
            continue
        if expected is not None and message.offset != expected:
            print(f"calibd pipe: {message.offset - expected} bytes of the stream lost at byte {expected} (this "
                  "client did not keep up)", file=sys.stderr)
        data = message.data if count is None else message.data[:count - written]
        out.write(data)
        out.flush()
        written, expected = written + len(data), message.offset + len(message.data)
    return 0


WATCH_REDRAW_S = 0.2  # a terminal is redrawn at most this often


def cmd_watch(args) -> int:
    """The daemon seen live: redrawn in place on a terminal, fitted to its width (looked up at each
    redraw: it may be resized), one line per event otherwise."""
    import shutil

    from .client import Client
    from .watchview import WatchView, render

    terminal = sys.stdout.isatty()
    view = WatchView(args.socket)

    def take(message) -> None:
        line = view.update(message, time.monotonic())
        if line and not terminal:
            print(line, flush=True)

    def watch() -> int:
        with Client.connect(args.socket, token=_token(args.token_file)) as client:
            take(client.version)
            take(client.watch(args.samples))
            client.command("DEVICE")  # answers (or a refusal) come with the stream
            client.command("POLL")
            drawn_s = -WATCH_REDRAW_S
            while True:
                wait_s = max(drawn_s + WATCH_REDRAW_S - time.monotonic(), 0.0) if terminal else None
                message = client.read(wait_s)
                if message is not None:
                    take(message)
                if terminal and time.monotonic() - drawn_s >= WATCH_REDRAW_S:
                    drawn_s = time.monotonic()
                    width = shutil.get_terminal_size().columns
                    sys.stdout.write("\x1b[H\x1b[2J" + "\n".join(render(view, drawn_s, width)) + "\n")
                    sys.stdout.flush()
    return _client_program(watch)


def cmd_trim(args) -> int:
    """A result's biases written into the sensor as its bias trim offsets, guarded (docs/trim.md)."""
    import serial

    from stim300.errors import PortError, Stim300Error
    from stim300.port import describe_error, open_serial, sigterm_as_ctrl_c

    from .results import load_result
    from .trim import (RestoreFailed, TrimOptions, VerifyFailed, load_backup, restore_backup, show,
                       trim_from_result, usage_checks)

    if sum(map(bool, (args.result, args.restore, args.show))) != 1:
        raise UsageError("trim: give one of --from RESULT.json, --restore BACKUP.json, --show")
    if args.show and (args.save or args.dry_run or args.force or args.verify is not None):
        raise UsageError("trim: --show only reads: it takes no --save, --dry-run, --force or --verify")
    if args.restore and (args.verify is not None or args.sensors is not None):
        raise UsageError("trim: --restore puts back every offset of the backup: it takes no --verify or --sensors")
    if args.yes and not args.save:
        raise UsageError("trim: --yes answers the question --save asks: give it with --save")
    if args.save and args.dry_run:
        raise UsageError("trim: --dry-run writes nothing, so there is nothing to --save")
    if args.save and not args.yes and not sys.stdin.isatty():
        raise UsageError("trim: --save asks for confirmation on the terminal: give --yes to save without asking")
    if not Path(args.backup_dir).is_dir():
        raise UsageError(f"trim: --backup-dir {args.backup_dir}: not a directory")
    options = TrimOptions(sensors=args.sensors or TrimOptions.sensors, force=args.force, dry_run=args.dry_run,
                          save=args.save, verify_s=args.verify, backup_dir=Path(args.backup_dir))
    result = load_result(args.result) if args.result else None
    backup = load_backup(args.restore) if args.restore else None
    if result is not None:
        usage_checks(result, options.sensors, options.verify_s)

    def say(text: str) -> None:
        print(f"calibd trim: {text}", file=sys.stderr, flush=True)

    def confirm(remaining_saves: int) -> bool:
        say(f"remaining flash saves: {remaining_saves} saves (rated to 10,000 in all)")
        if args.yes:
            return True
        print("write these trims to the sensor's flash? [y/N] ", end="", file=sys.stderr, flush=True)
        return sys.stdin.readline().strip().lower() in ("y", "yes")

    try:
        with sigterm_as_ctrl_c(), open_serial(args.port, args.baud) as ser:  # kill: the backup is put back too
            if args.show:
                rows = show(ser, options)
            elif result is not None:
                rows = trim_from_result(ser, result, options, say, confirm, say)
            else:
                rows = restore_backup(ser, backup, args.restore, options, say, confirm, say)
    except (PortError, VerifyFailed, RestoreFailed) as exc:
        raise RunError(f"trim: {exc}") from None
    except Stim300Error as exc:
        raise RunError(f"trim: {args.port}: {exc}") from None
    except (serial.SerialException, OSError) as exc:
        raise RunError(f"trim: {args.port}: {describe_error(exc)}") from None
    print("\n".join(rows))
    return 0


def _sensors(text: str) -> tuple[str, ...]:
    from stim300.trim import SENSORS

    names = tuple(dict.fromkeys(name.strip() for name in text.split(",")))
    unknown = [name for name in names if name not in SENSORS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"{text!r}: a comma-separated list of {', '.join(SENSORS)}")
    return names


def _add_trim_parser(sub) -> None:
    from stim300.protocol import DEFAULT_BIT_RATE

    p = sub.add_parser("trim", help="write a result's biases into the sensor as its bias trim offsets (docs/trim.md)")
    p.add_argument("port", help="device path (/dev/ttyUSB0) or pyserial URL; the daemon must not hold it")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--from", dest="result", metavar="RESULT.json", help="the result whose biases to take off")
    what.add_argument("--restore", metavar="BACKUP.json", help="put back exactly the offsets of a backup file")
    what.add_argument("--show", action="store_true", help="print the trims in force, the reference, the saves left")
    p.add_argument("--sensors", type=_sensors, help="with --from: which triads to trim (default gyro,acc,incl)")
    p.add_argument("--dry-run", action="store_true", help="print what would be written; write nothing")
    p.add_argument("--force", action="store_true", help="trim despite the refusals (each is warned)")
    p.add_argument("--save", action="store_true", help="after the check, save to flash (asks first; uses one of "
                                                       "the unit's rated saves)")
    p.add_argument("--yes", action="store_true", help="with --save: do not ask")
    p.add_argument("--verify", type=_number(1, 3600, "s"), metavar="S",
                   help="after the volatile trim, check S seconds of static data at the home position "
                        "(residual gyro biases within 2 sigma); save only when it passes")
    p.add_argument("--backup-dir", default=".", help="where trim-backup-*.json goes (default: here)")
    p.add_argument("--baud", type=_positive_int, default=DEFAULT_BIT_RATE,
                   help=f"bit/s the sensor runs at (default {DEFAULT_BIT_RATE})")
    p.set_defaults(func=cmd_trim)


def _add_client_commands(sub) -> None:
    """`calibd pipe` and `calibd watch`: programs reading the daemon's socket ([serve] socket)."""
    where = "the daemon's socket: a path ([serve] socket, e.g. /run/calibd/ttyUSB0/calibd.sock) or HOST:PORT"
    token = "TCP served with a token: the file holding it ([serve] tcp_token_file), sent first"
    p = sub.add_parser("pipe", help="the daemon's socket messages as JSON lines on stdout (like gpspipe -w)")
    p.add_argument("socket", help=where)
    p.add_argument("--samples", choices=SAMPLE_KINDS, default="none",
                   help="also SAMPLES messages of the raw or bias-corrected stream (default none)")
    p.add_argument("--raw", action="store_true", help="also RAW messages: the sensor's bytes, base64")
    p.add_argument("--bytes", action="store_true",
                   help="only the sensor's bytes as read, binary (a capture: calibd pipe SOCKET --bytes > x.bin)")
    p.add_argument("-n", "--count", type=_positive_int, metavar="COUNT",
                   help="stop after COUNT messages (the VERSION and WATCH answers count); with --bytes COUNT bytes")
    p.add_argument("--token-file", metavar="PATH", help=token)
    p.set_defaults(func=cmd_pipe)
    p = sub.add_parser("watch", help="the daemon live: state, campaign progress, estimates with sigma, stream "
                                     "health (like gpsmon)")
    p.add_argument("socket", help=where)
    p.add_argument("--samples", choices=SAMPLE_KINDS, default="none",
                   help="also watch samples: the rate served, the last sample and 1-s means (default none)")
    p.add_argument("--token-file", metavar="PATH", help=token)
    p.set_defaults(func=cmd_watch)


SPEED_RANGE = (1e-3, 1e6)  # times real time: slower would take years, faster is `max`


def _speed(text: str) -> str:
    if text == "max":
        return text
    try:
        if SPEED_RANGE[0] <= float(text) <= SPEED_RANGE[1]:  # nan and inf fail too
            return text
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"{text!r} is not 'max' or a factor of real time in "
                                     f"[{SPEED_RANGE[0]:g}, {SPEED_RANGE[1]:g}]")


TOPIC_HELP = ("the sensor_msgs/Imu topic of a recording (ROS bag, rosbag2, MCAP; docs/recordings.md) (default: its "
              "only one)")


def _index_settings(args, command: str) -> dict:
    """The joint method's index settings from --index-step and --index-sigma (`_add_index_options`)."""
    if args.index_sigma is not None and args.index_step is None:
        raise UsageError(f"{command}: --index-sigma is the index's 1-sigma: give --index-step too")
    return {"index_step_deg": args.index_step, "index_sigma_deg": args.index_sigma}


def _add_index_options(p: argparse.ArgumentParser) -> None:
    """The joint method's indexing table (`calibrate`, `batch`, `plan`)."""
    from .methods.base import DEFAULT_INDEX_SIGMA_DEG, INDEX_SIGMA_DEG, INDEX_STEP_DEG

    p.add_argument("--index-step", type=_number(*INDEX_STEP_DEG, "deg"), metavar="DEG",
                   help="joint: the platform's turns are whole multiples of DEG (an indexing table's step): each "
                        "static's angle is taken from its stop, and the turns show the gyro Z scale factor")
    p.add_argument("--index-sigma", type=_number(*INDEX_SIGMA_DEG, "deg"), metavar="DEG",
                   help=f"joint: how exactly a static sits at its stop, 1-sigma (default {DEFAULT_INDEX_SIGMA_DEG:g} "
                        "deg)")


def _add_remount_options(p: argparse.ArgumentParser, planned: bool = False) -> None:
    """The unit's second mounting: its capture (`calibrate`), or the campaign planned on it too (`plan`)."""
    from .methods.base import DEFAULT_REMOUNT_SIGMA_DEG, REMOUNT_SIGMA_DEG

    if planned:
        p.add_argument("--remounted", action="store_true",
                       help="the campaign run again with the housing turned 180 deg about its own Z axis (a second "
                            "mounting, calibrate --remounted): what it buys pitch, roll, alpha and beta")
    else:
        p.add_argument("--remounted", metavar="CAPTURE",
                       help="joint: the same unit's campaign with its housing turned 180 deg about its own Z axis "
                            "on the interface: the two tilts show the gyro misalignment that tilts the platform "
                            "axis, and pitch, roll, alpha and beta lose it (docs/turntable.md, A second mounting)")
    p.add_argument("--remount-sigma", type=_number(*REMOUNT_SIGMA_DEG, "deg"), metavar="DEG",
                   help=f"how exactly the fixture turns the housing by 180 deg, 1-sigma (default "
                        f"{DEFAULT_REMOUNT_SIGMA_DEG:g} deg)")


def _add_intrinsics_option(p: argparse.ArgumentParser, gain: str) -> None:
    """The unit's known factory terms (`calibrate`, `plan`; the daemon's `[method] intrinsics`)."""
    p.add_argument("--intrinsics", type=path_arg, metavar="RESULT.json", action="append",
                   help="the factory terms an earlier result of this unit estimated (a bench campaign's six "
                        f"positions, a second mounting), taken as known; {gain}; repeat for several results "
                        "(docs/turntable.md, Factory terms known from an earlier calibration)")


def _add_method_options(p: argparse.ArgumentParser, methods: tuple[str, ...]) -> None:
    """The options that say how a capture is calibrated (`calibrate`, `batch`)."""
    p.add_argument("--method", choices=methods, default="joint",
                   help="joint: every segment in one fit, with 1-sigma (default); thesis: the thesis's chain")
    _add_site_options(p, required=True)
    p.add_argument("--alpha", type=_number(-10, 10, "deg"), help="a-priori interface tilt alpha, deg (nominal run)")
    p.add_argument("--beta", type=_number(-10, 10, "deg"), help="a-priori interface tilt beta, deg (nominal run)")
    p.add_argument("--platform-rate", type=_magnitude(*PLATFORM_RATE_DEG_S, "deg/s"),
                   help="platform rate of the full turn from telemetry, deg/s, signed, magnitude "
                        f"{PLATFORM_RATE_DEG_S[0]:g} to {PLATFORM_RATE_DEG_S[1]:g} (default: from the gyros)")
    p.add_argument("--bench", action="store_true", help="a bench session: six-position biases and alpha/beta")
    p.add_argument("--start", type=_number(0, 1e9, "s"),
                   help="start S seconds into the power-up (default: where the warm-up rule says the temperature "
                        "has settled)")
    p.add_argument("--fixed-amplitude", action="store_true",
                   help="joint: fix the horizontal Earth rate to Omega_E cos(lat) (better yaw on short data; "
                        "loses the check that the Earth rate is really seen)")
    p.add_argument("--drift", action="store_true",
                   help="joint: fit a linear gyro drift per channel (thermal ramps); costs precision")
    _add_index_options(p)
    p.add_argument("--topic", type=_ros_topic, metavar="NAME", help=TOPIC_HELP)


def build_parser() -> argparse.ArgumentParser:
    from .methods import DAEMON_METHODS
    from .warmup import WINDOW_RANGE_S

    parser = CommandParser(prog="calibd", description="STIM300 calibration: calibrate captures, simulate sessions.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=CommandParser)
    p = sub.add_parser("calibrate", help="capture -> biases and alignment (result JSON)")
    p.add_argument("capture")
    p.add_argument("-o", "--output", type=path_arg, required=True, help="RESULT.json (replaced atomically)")
    _add_method_options(p, DAEMON_METHODS)
    p.add_argument("--power-up", type=_positive_int, metavar="N", dest="power_up",
                   help="calibrate power-up N (1-based) of a capture in which the sensor restarted (default: the "
                        "last one that has what the method needs)")
    p.add_argument("--session", type=_positive_int, dest="power_up", help=argparse.SUPPRESS)  # its former name
    _add_remount_options(p)
    _add_intrinsics_option(p, "joint: what they limit falls to the noise")
    p.set_defaults(func=cmd_calibrate)
    p = sub.add_parser("batch", help="captures and folders of captures -> every power-up calibrated on Dask, one "
                                     "row each in a fleet table (Parquet; docs/fleet.md)")
    p.add_argument("captures", nargs="+", metavar="CAPTURE|DIR",
                   help="capture files (raw or recordings) and folders of them (walked, sorted)")
    p.add_argument("-o", "--output", type=path_arg, required=True,
                   help="FLEET.parquet: rows are added; captures already in it are skipped (replaced atomically)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask cluster: tcp://HOST:PORT or the scheduler file of `dask scheduler "
                        "--scheduler-file` (default: a local cluster)")
    p.add_argument("--workers", type=_positive_int, metavar="N",
                   help="worker processes of the local cluster (default: one per core)")
    p.add_argument("--redo", action="store_true", help="calibrate the captures already in the table again")
    _add_method_options(p, DAEMON_METHODS)
    p.set_defaults(func=cmd_batch)
    p = sub.add_parser("fleet", help="a fleet table -> each sensor's history, its run-to-run spread against the "
                                     "datasheet, units and estimates out of family (docs/fleet.md)")
    p.add_argument("table", metavar="FLEET.parquet", help="the table calibd batch wrote")
    p.add_argument("--html", type=path_arg, metavar="REPORT.html",
                   help="also write a self-contained HTML report with each estimate's history (needs matplotlib)")
    p.add_argument("--serial", metavar="SN", help="only this serial number")
    p.set_defaults(func=cmd_fleet)
    p = sub.add_parser("run", help="the daemon: read the port, calibrate after every power-up")
    p.add_argument("--config", type=path_arg, required=True,
                   help="TOML configuration: [serial], [site], [output], [warmup], [detection], [method], [serve] "
                        "(README, calibd run)")
    p.add_argument("--port", help="serial port overriding the configuration's (the systemd unit passes /dev/%%i)")
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("replay", help="the daemon's pipeline on a capture, printing states and results")
    p.add_argument("capture", help="a STIM300 capture, or a recording of its Imu messages (ROS bag, rosbag2, MCAP), "
                                   "replayed as the datagrams they stand for (docs/recordings.md)")
    p.add_argument("--config", type=path_arg, help="TOML configuration (site, warm-up, method)")
    _add_site_options(p, required=False)
    p.add_argument("--speed", type=_speed,
                   help="N times real time, or max (default; with --serve: 1, as the sensor sends)")
    p.add_argument("--pty", action="store_true",
                   help="write the capture into a pseudo-terminal read by the daemon's own port reader")
    p.add_argument("--serve", action="store_true",
                   help="serve the replayed sensor as calibd run does, by the [serve] table of --config (through "
                        "a pseudo-terminal, paced; docs/serving.md)")
    p.add_argument("--socket", type=path_arg, help="serve the socket protocol at this path (implies --serve)")
    p.add_argument("--raw-pty", type=path_arg,
                   help="serve the raw bytes on a pty linked at this path (implies --serve)")
    p.add_argument("--corrected-pty", type=path_arg,
                   help="serve corrected datagrams on a pty linked at this path (implies --serve)")
    p.add_argument("--warmup-window", type=_number(*WINDOW_RANGE_S, "s"),
                   help="seconds of settled temperature that end the warm-up (default 600)")
    p.add_argument("--state-dir", type=path_arg, help="also write result.json, history/ and state.json there")
    p.add_argument("--mcap", type=path_arg, metavar="VIEW.mcap",
                   help="record the Foxglove view's channels (the IMU, state, estimates, health, results) into "
                        "VIEW.mcap, replaced atomically at the end; needs the foxglove extra (docs/foxglove.md)")
    p.add_argument("--topic", type=_ros_topic, metavar="NAME", help=TOPIC_HELP)
    p.set_defaults(func=cmd_replay)
    p = sub.add_parser("status", help="the daemon's state and last result")
    p.add_argument("--state-dir", type=path_arg, required=True)
    p.add_argument("--json", action="store_true", help="one JSON object: the state and the result document")
    p.add_argument("-f", "--follow", action="store_true",
                   help="keep printing: again each time state.json or result.json changes (with --json: one JSON "
                        "object per line); Ctrl-C ends")
    p.set_defaults(func=cmd_status)
    p = sub.add_parser("sensitivity", help="what alpha/beta errors do to the thesis method's estimates "
                                           "(docs/thesis-estimators.md)")
    p.add_argument("--alpha-error", type=_number(-10, 10, "deg"), required=True, help="d_alpha, deg")
    p.add_argument("--beta-error", type=_number(-10, 10, "deg"), required=True, help="d_beta, deg")
    p.add_argument("--platform-rate", type=_number(-1000, 1000, "deg/s"), required=True, help="deg/s")
    _add_site_options(p, required=True)
    p.set_defaults(func=cmd_sensitivity)
    p = sub.add_parser("report", help="result + its capture -> HTML report with figures (needs matplotlib)")
    p.add_argument("result", help="RESULT.json written by calibd calibrate")
    p.add_argument("capture", help="the capture the result was made from")
    p.add_argument("-o", "--output", type=path_arg, required=True,
                   help="report.html (self-contained); the figures also go to report_files/*.png (and *.svg with "
                        "--svg) beside it")
    p.add_argument("--svg", action="store_true", help="also write each figure's vector copy, report_files/*.svg")
    p.add_argument("--topic", type=_ros_topic, metavar="NAME",
                   help="a recording's sensor_msgs/Imu topic (default: the one the result was made from)")
    p.set_defaults(func=cmd_report)
    p = sub.add_parser("plan", help="campaign + site + noise -> expected 1-sigma of every estimate, time to a "
                                    "target yaw 1-sigma (docs/planner.md)")
    _add_site_options(p, required=False, optional_when="needed with --campaign; replaces a scenario's [site]")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--campaign", help="a built-in campaign: thesis, continuous or index")
    which.add_argument("--protocol", dest="campaign", help=argparse.SUPPRESS)  # its former name
    which.add_argument("--scenario", metavar="SCENARIO.toml",
                       help="your own campaign: a scenario file as calibd simulate takes (its statics and turns, "
                            "its [site] unless --latitude is given, its [noise] unless noise options are given)")
    p.add_argument("--target-yaw-deg", type=_number(0.001, 90, "deg"), default=1.0,
                   help="yaw 1-sigma to reach, deg (default 1)")
    p.add_argument("--noise", type=path_arg,
                   help="NOISE.json (calibd.noise/1, from calibd noise) instead of the figures below")
    _add_index_options(p)
    _add_remount_options(p, planned=True)
    _add_intrinsics_option(p, "what they buy the campaign")
    for option, (field, unit, what) in PLAN_NOISE_OPTIONS.items():
        stim300 = getattr(spec.NoiseFigures(), field)
        p.add_argument(option, dest=field, type=_number(0, 1000, unit), metavar=unit.upper(),
                       help=f"{what}, {unit} (default: the scenario's [noise], else the STIM300's {stim300:g} {unit})")
    p.set_defaults(func=cmd_plan)
    p = sub.add_parser("noise", help="capture -> Allan deviation of every channel from its statics, noise figures")
    p.add_argument("capture")
    p.add_argument("-o", "--output", type=path_arg, help="NOISE.json (calibd.noise/1, replaced atomically)")
    p.add_argument("--kalibr", type=path_arg, metavar="IMU.yaml",
                   help="Kalibr's imu.yaml: noise densities and random walks in SI units, update_rate (replaced "
                        "atomically; docs/noise.md)")
    p.add_argument("--rostopic", type=_ros_topic,
                   help="rostopic written to the Kalibr file (default: a recording's topic, else /imu0)")
    p.add_argument("--start", type=_number(0, 1e9, "s"), default=0.0, help="skip the first S seconds (warm-up)")
    p.add_argument("--topic", type=_ros_topic, metavar="NAME", help=TOPIC_HELP)
    p.set_defaults(func=cmd_noise)
    p = sub.add_parser("apply", help="result + capture -> bias-corrected samples in SI units (NPZ, CSV or MCAP)")
    p.add_argument("result", help="RESULT.json written by calibd calibrate or the daemon")
    p.add_argument("capture", help="a capture of the same sensor (and power-up) to correct, or a recording of its "
                                   "Imu messages (ROS bag, rosbag2, MCAP)")
    p.add_argument("-o", "--output", type=path_arg, required=True,
                   help="OUT.npz, OUT.csv or OUT.mcap (ROS 2 sensor_msgs/Imu; replaced atomically)")
    p.add_argument("--topic", type=_ros_topic, metavar="NAME", help=TOPIC_HELP)
    p.add_argument("--frame", action="store_true",
                   help="turn the vectors into the home frame: NWU when the platform is at its home position, "
                        "turning with the platform (needs yaw, pitch and roll)")
    p.add_argument("--force", action="store_true",
                   help="apply a result of another sensor or with poor estimates anyway (warned)")
    p.set_defaults(func=cmd_apply)
    p = sub.add_parser("simulate", help="scenario -> capture file and CAPTURE.truth.json")
    p.add_argument("scenario", help=f"scenario TOML file, or one of: {', '.join(READY_MADE)}")
    p.add_argument("-o", "--output", type=path_arg, required=True, help="capture file to write")
    p.set_defaults(func=cmd_simulate)
    _add_trim_parser(sub)
    _add_client_commands(sub)
    return parser


def main(argv=None) -> int:
    return run_command(build_parser(), argv, input_errors=(CalibdError,))


if __name__ == "__main__":
    sys.exit(main())
