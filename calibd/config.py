"""The daemon's configuration: a TOML file -> a validated, frozen `DaemonConfig`.

A daemon finds its mistakes in the journal, long after it was started; so everything is checked
at start-up, unknown tables and keys included (a misspelt key would otherwise silently keep its
default), and each error is one line naming the file, the table, the key, the value and what
was expected.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path, PurePath

from stim300.cliutil import TEXT_LIMIT_BYTES, read_text
from stim300.errors import UsageError
from stim300.protocol import DEFAULT_BIT_RATE
from stim300.trim import SENSORS

from .methods import DAEMON_METHODS, OptionError, estimator
from .serve.protocol import IDLE_TIMEOUT_S, MAX_CLIENTS, MAX_CLIENTS_PER_UID, host_port
from .documents import Table, parse_toml, site_from_table
from .warmup import WINDOW_RANGE_S, WarmupConfig
from .errors import CalibdError
from .frames import Site

METHODS = DAEMON_METHODS  # the estimators (calibd.estimators) the daemon runs
TABLES = ("serial", "site", "output", "warmup", "detection", "method", "trim", "serve", "ros2", "foxglove", "record")
# what the daemon serves or records: started once, kept as started on SIGHUP
SERVED_TABLES = ("serve", "ros2", "foxglove", "record")


class ConfigError(CalibdError):
    """A configuration the daemon cannot run with; the message says where and why in one line."""


@dataclass(frozen=True)
class SerialConfig:
    port: str  # device path or pyserial URL
    baudrate: int = DEFAULT_BIT_RATE


@dataclass(frozen=True)
class DetectionConfig:
    """Segment detection settings (calibd.detect.find_segments); None keeps its default, and the
    thresholds' default is to follow the sensor's own noise."""

    turn_threshold_deg_s: float | None = None  # gyro average above which the platform moves
    remount_g: float | None = None  # accelerometer jump between quiet stretches that is a re-mount
    min_static_s: float | None = None  # shortest static kept (default 5 s)
    settle_s: float | None = None  # trimmed off a static next to motion (default 1 s)

    def options(self) -> dict:
        return {key: value for key, value in asdict(self).items() if value is not None}


@dataclass(frozen=True)
class MethodConfig:
    """The estimator and its options (see `calibd calibrate --help` for what they mean): the
    settings of every daemon method (calibd.methods, Estimator.settings), None or False where
    not given, for the method's own Estimator.options."""

    name: str = "joint"
    fixed_amplitude: bool = False  # joint only
    drift: bool = False  # joint only
    alpha_deg: float | None = None  # thesis only, with beta_deg: a-priori interface tilt (nominal run)
    beta_deg: float | None = None
    resolve_every_s: float = 60.0  # how often the estimate is recomputed from the data so far
    index_step_deg: float | None = None  # joint only: the platform's turns are whole multiples of this angle
    index_sigma_deg: float | None = None  # joint only: how exactly a static sits at its stop (default 0.01 deg)
    intrinsics: list[str] | None = None  # joint only: result files of this unit whose factory terms are known


BEFORE_RESULT = ("hold", "raw")  # what the corrected outputs carry before the power-up's first result
CORRECTIONS = ("latest", "first", "best")  # which of the power-up's results the corrected outputs subtract


@dataclass(frozen=True)
class ServeConfig:
    """What the daemon serves to the other programs of the host (docs/serving.md); nothing when
    every path is None."""

    raw_pty: Path | tuple[Path, ...] | None = None  # symlink(s) to ptys carrying the sensor's bytes unchanged
    corrected_pty: Path | None = None  # a symlink to a pty carrying bias-corrected datagrams
    corrected_before_result: str = "hold"  # "hold": nothing corrected before a result; "raw": raw data
    correction: str = "latest"  # which result of the power-up is subtracted (calibd.correction.replaces)
    allow_service_mode: bool = False  # SERVICEMODE, UTILITYMODE and R written into a raw pty reach the sensor
    socket: Path | None = None  # Unix stream socket speaking calibd.serve.protocol
    tcp: tuple[str, int] | None = None  # (host, port) of the same protocol on TCP
    tcp_token_file: Path | None = None  # the shared secret a TCP client sends with ?AUTH first
    tcp_open: bool = False  # TCP without a token: open to every local user
    group: str | None = None  # group of the socket, the ptys and the result copy
    result_copy: Path | None = None  # a group-readable copy of result.json
    idle_timeout_s: float = IDLE_TIMEOUT_S  # a client with no command and nothing read this long is closed
    max_clients_per_uid: int = MAX_CLIENTS_PER_UID  # connections of one user (TCP clients together)

    @property
    def raw_ptys(self) -> tuple[Path, ...]:
        """The raw ptys' links: raw_pty as one path or several (one pty serves one reader)."""
        if self.raw_pty is None:
            return ()
        if isinstance(self.raw_pty, (str, PurePath)):
            return (Path(self.raw_pty),)
        return tuple(map(Path, self.raw_pty))

    @property
    def serving(self) -> bool:
        return any(v is not None for v in (self.raw_pty, self.corrected_pty, self.socket, self.tcp, self.result_copy))


def parse_tcp(text: str) -> tuple[str, int] | None:
    """[serve] tcp: "HOST:PORT" ("[V6]:PORT"), or "PORT" alone for the loopback address ->
    (host, port); None when malformed (the socket protocol's one rule, `host_port`)."""
    try:
        return host_port(text, "127.0.0.1")
    except ValueError:
        return None


@dataclass(frozen=True)
class Ros2Config:
    """ROS 2 topics published over DDS (docs/ros2.md); an empty [ros2] table takes these."""

    domain_id: int = 0  # ROS_DOMAIN_ID of the subscribers
    frame_id: str = "imu_link"  # every message's header.frame_id: the IMU's housing axes
    data_raw_topic: str = "imu/data_raw"  # sensor_msgs/Imu as the sensor sent it, SI
    data_topic: str = "imu/data"  # sensor_msgs/Imu with the served correction's biases taken out
    calibration_topic: str = "imu/calibration"  # std_msgs/String: the result document (latched)
    alignment_topic: str = "imu/alignment"  # geometry_msgs/QuaternionStamped: the IMU in ENU (latched)
    diagnostics_topic: str = "diagnostics"  # diagnostic_msgs/DiagnosticArray at 1 Hz

    TOPICS = ("data_raw_topic", "data_topic", "calibration_topic", "alignment_topic", "diagnostics_topic")


@dataclass(frozen=True)
class FoxgloveConfig:
    """The Foxglove live view's WebSocket server (docs/foxglove.md); an empty [foxglove] table
    takes these."""

    host: str = "127.0.0.1"  # loopback: the host's own Foxglove (an SSH tunnel from elsewhere)
    port: int = 8765
    rate_hz: float = 100.0  # the IMU channels' display rate (block averages of the samples)


@dataclass(frozen=True)
class RecordConfig:
    """The daemon's recording of the sensor (docs/recordings.md): its bytes and samples into
    MCAP files in `directory`, a new file every `rotate_s` or `rotate_mb`, the newest `keep`
    kept (0: all)."""

    directory: Path
    rotate_s: float = 3600.0
    rotate_mb: float = 1024.0
    keep: int = 24
    frame_id: str = "imu_link"  # the Imu messages' header.frame_id


TRIM_APPLY = ("off", "volatile")  # never "flash": a daemon spends no flash saves (docs/trim.md)


@dataclass(frozen=True)
class TrimConfig:
    """Whether the daemon writes a good result's biases into the sensor as volatile bias trims
    (docs/trim.md), and which triads: the gyros by default, whose run-to-run bias is the largest
    and the best known."""

    apply: str = "off"
    sensors: tuple[str, ...] = ("gyro",)


@dataclass(frozen=True)
class DaemonConfig:
    serial: SerialConfig
    site: Site
    state_dir: Path
    warmup: WarmupConfig
    method: MethodConfig
    detection: DetectionConfig = DetectionConfig()
    trim: TrimConfig = TrimConfig()
    serve: ServeConfig = ServeConfig()
    ros2: Ros2Config | None = None  # None: no [ros2] table, nothing published over DDS
    foxglove: FoxgloveConfig | None = None  # None: no [foxglove] table, no live view
    record: RecordConfig | None = None  # None: no [record] table, nothing recorded

    @property
    def serving(self) -> bool:
        """Whether the daemon serves the sensor at all (the socket, ptys, ROS 2, Foxglove, a recording)."""
        return bool(self.served_tables)

    @property
    def served_tables(self) -> list[str]:
        """The SERVED_TABLES given, as "[name]"."""
        return [f"[{name}]" for name in SERVED_TABLES if getattr(self, name) not in (None, ServeConfig())]

    def with_port(self, port: str) -> DaemonConfig:
        """A copy on another serial port: one file serves every instance of the systemd
        template unit, which passes `--port /dev/%i`."""
        return replace(self, serial=replace(self.serial, port=port))


class _ConfigTable(Table):
    """A configuration's table: ConfigError, and required keys."""

    def __init__(self, data: dict, where: str):
        super().__init__(data, where, ConfigError)

    def require(self, key: str, kind, check, expect: str):
        value = self.get(key, None, kind, check, expect)
        if value is None:  # TOML has no null: None means the key is absent
            self.missing(key, f"expected {expect}")
        return value


# Sane ranges: a value far outside is a typo or a unit mistake, and 1e-300 or 1e308 would make the
# daemon re-solve without pause or never end its warm-up.
DAY_S = 86400.0
RESOLVE_EVERY_S = (1.0, DAY_S)
MAX_BIT_RATE = 10_000_000  # far above the STIM300's fastest (1843200 bit/s)


def _within(low: float, high: float, low_open: bool = False):
    """A check that a value lies in [low, high] ((low, high] with `low_open`)."""
    return lambda v: (low < v if low_open else low <= v) and v <= high


def _range_words(what: str, low: float, high: float, unit: str, low_open: bool = False) -> str:
    return f"{what} in {'(' if low_open else '['}{low:g}, {high:g}] {unit}"


def _nonempty(s: str) -> bool:
    return s.strip() != ""


def _positive(x) -> bool:
    return x > 0


def _serial(t: _ConfigTable) -> SerialConfig:
    serial = SerialConfig(
        port=t.require("port", str, _nonempty, "a device path such as \"/dev/ttyUSB0\" or a pyserial URL"),
        baudrate=t.get("baudrate", DEFAULT_BIT_RATE, int, _within(0, MAX_BIT_RATE, True),
                       _range_words("a positive bit rate", 0, MAX_BIT_RATE, "bit/s", True)))
    t.finish()
    return serial


def _state_dir(t: _ConfigTable) -> Path:
    state_dir = Path(t.require("state_dir", str, _nonempty, "a directory path for the daemon's state"))
    t.finish()
    return state_dir


def _warmup(t: _ConfigTable) -> WarmupConfig:
    d = WarmupConfig()
    warmup = WarmupConfig(
        max_slope_c_per_h=t.get("max_slope_c_per_h", d.max_slope_c_per_h, float, _within(0, 100, True),
                                _range_words("a positive temperature slope", 0, 100, "degC/h", True)),
        window_s=t.get("window_s", d.window_s, float, _within(*WINDOW_RANGE_S),
                       _range_words("a duration", *WINDOW_RANGE_S, "s")),
        min_time_s=t.get("min_time_s", d.min_time_s, float, _within(0, 7 * DAY_S),
                         _range_words("a duration", 0, 7 * DAY_S, "s")))
    t.finish()
    return warmup


def _detection(t: _ConfigTable) -> DetectionConfig:
    def positive(key: str, what: str, high: float, unit: str, allow_zero: bool = False):
        words = f"a {'non-negative' if allow_zero else 'positive'} {what}"
        return t.get(key, None, float, _within(0, high, not allow_zero),
                     _range_words(words, 0, high, unit, not allow_zero))
    detection = DetectionConfig(turn_threshold_deg_s=positive("turn_threshold_deg_s", "rate", 1000, "deg/s"),
                                remount_g=positive("remount_g", "acceleration step", 10, "g"),
                                min_static_s=positive("min_static_s", "duration", DAY_S, "s"),
                                settle_s=positive("settle_s", "duration", 3600, "s", allow_zero=True))
    t.finish()
    return detection


def _method(t: _ConfigTable) -> MethodConfig:
    """The method's name, its own settings as its Estimator declares them, and resolve_every_s;
    a setting of another daemon method is refused, naming the method it belongs to."""
    d = MethodConfig()
    name = t.get("name", d.name, str, lambda n: n in METHODS, " or ".join(f'"{m}"' for m in METHODS))
    method = estimator(name)
    own = {key: t.get(key, getattr(d, key), s.kind, s.check, s.expect) for key, s in method.settings.items()}
    resolve_every_s = t.get("resolve_every_s", d.resolve_every_s, float, _within(*RESOLVE_EVERY_S),
                            _range_words("an interval", *RESOLVE_EVERY_S, "s"))
    owners = {key: other for other in METHODS for key in estimator(other).settings if key not in method.settings}
    for key in t.data:
        if key in owners:
            t.fail(key, f"{t.data[key]!r} is not allowed with name = \"{name}\": it is an option of the "
                        f"{owners[key]} method")
    t.finish()
    try:
        method.options(own)
    except OptionError as exc:
        t.fail(exc.key, exc.reason)
    return MethodConfig(name, resolve_every_s=resolve_every_s, **own)


def _distinct_triads(value: list) -> bool:
    names = [v for v in value if isinstance(v, str) and v in SENSORS]
    return value != [] and len(names) == len(value) == len(set(names))


def _trim(t: _ConfigTable) -> TrimConfig:
    d = TrimConfig()
    choices = " or ".join(f'"{v}"' for v in TRIM_APPLY)
    apply = t.get("apply", d.apply, str, lambda v: v in TRIM_APPLY,
                  f'{choices} (never "flash": a daemon spends no flash saves)')
    sensors = t.get("sensors", list(d.sensors), list, _distinct_triads,
                    "a list of distinct triads among " + ", ".join(f'"{v}"' for v in SENSORS))
    t.finish()
    return TrimConfig(apply, tuple(sensors))


def _path_text(value) -> bool:
    return isinstance(value, str) and _nonempty(value) and "\0" not in value


def _paths(value) -> bool:
    """A path, or a non-empty list of paths."""
    return _path_text(value) or (isinstance(value, list) and value != [] and all(map(_path_text, value)))


def _serve(t: _ConfigTable) -> ServeConfig:
    def path(key: str, what: str) -> Path | None:
        value = t.get(key, None, str, _path_text, f"a path for {what}")
        return None if value is None else Path(value)
    tcp = t.get("tcp", None, str, lambda v: parse_tcp(v) is not None,
                'an address "HOST:PORT" (e.g. "127.0.0.1:2950"; PORT in [1, 65535])')
    raw = t.get("raw_pty", None, object, _paths, "a path, or a list of paths, for the raw ptys' links")
    serve = ServeConfig(
        raw_pty=None if raw is None else Path(raw) if isinstance(raw, str) else tuple(map(Path, raw)),
        corrected_pty=path("corrected_pty", "the corrected pty's link"),
        corrected_before_result=t.get("corrected_before_result", "hold", str, lambda v: v in BEFORE_RESULT,
                                      " or ".join(f'"{v}"' for v in BEFORE_RESULT)),
        correction=t.get("correction", "latest", str, lambda v: v in CORRECTIONS,
                         " or ".join(f'"{v}"' for v in CORRECTIONS)),
        allow_service_mode=t.get("allow_service_mode", False, bool),
        socket=path("socket", "the Unix socket"), tcp=None if tcp is None else parse_tcp(tcp),
        tcp_token_file=path("tcp_token_file", "the TCP clients' token"), tcp_open=t.get("tcp_open", False, bool),
        group=t.get("group", None, str, _nonempty, "a group name such as \"stim300\""),
        result_copy=path("result_copy", "the result's copy"),
        idle_timeout_s=t.get("idle_timeout_s", IDLE_TIMEOUT_S, float, _within(0, DAY_S, True),
                             _range_words("a timeout", 0, DAY_S, "s", True)),
        max_clients_per_uid=t.get("max_clients_per_uid", MAX_CLIENTS_PER_UID, int, _within(1, MAX_CLIENTS),
                                  f"a number of connections in [1, {MAX_CLIENTS}]"))
    t.finish()
    if serve.tcp is not None and serve.tcp_token_file is None and not serve.tcp_open:
        t.fail("tcp", "needs tcp_token_file = PATH (clients send ?AUTH with its token first) or tcp_open = true "
                      "(every local user may connect)")
    if serve.tcp_token_file is not None and serve.tcp_open:
        t.fail("tcp_open", "true with tcp_token_file: choose one (a token, or TCP open to every local user)")
    for key in ("tcp_token_file", "tcp_open"):
        if getattr(serve, key) and serve.tcp is None:
            t.fail(key, "given without tcp: it applies to TCP clients only")
    seen: dict[Path, str] = {}
    paths = [("raw_pty", link) for link in serve.raw_ptys]
    paths += [(key, getattr(serve, key)) for key in ("corrected_pty", "socket", "result_copy")]
    for key, value in paths:
        if value in seen:
            t.fail(key, f"{str(value)!r} is also {seen[value]}: each served path must be its own")
        if value is not None:
            seen[value] = key
    return serve


MAX_RATE_HZ = 2000.0  # the sensor's fastest


def _ros2(t: _ConfigTable) -> Ros2Config:
    """[ros2]: domain, frame and topic names, each checked by the ROS 2 rules (calibd.ros2.messages,
    which needs no DDS package to check them)."""
    from stim300.errors import FormatError
    from stim300.rosimu import check_frame_id

    from .ros2.messages import MAX_DOMAIN_ID, Ros2Error, dds_topic

    def name(key: str, check) -> str:
        value = t.get(key, getattr(d, key), str)
        try:
            check(value)
        except (Ros2Error, FormatError) as exc:  # the topic rules are calibd's, the frame_id's the driver's
            why = str(exc).split(": ", 1)[1]
            t.fail(key, why if repr(value) in why else f"{value!r}: {why}")
        return value

    d = Ros2Config()
    ros2 = Ros2Config(domain_id=t.get("domain_id", d.domain_id, int, _within(0, MAX_DOMAIN_ID),
                                      f"a DDS domain id in [0, {MAX_DOMAIN_ID}]"),
                      frame_id=name("frame_id", check_frame_id),
                      **{key: name(key, lambda v, key=key: dds_topic(v, key)) for key in Ros2Config.TOPICS})
    t.finish()
    seen: dict[str, str] = {}
    for key in Ros2Config.TOPICS:
        topic = dds_topic(getattr(ros2, key), key)
        if topic in seen:
            t.fail(key, f"{getattr(ros2, key)!r} is also {seen[topic]}: each topic must be its own")
        seen[topic] = key
    return ros2


def _foxglove(t: _ConfigTable) -> FoxgloveConfig:
    d = FoxgloveConfig()
    foxglove = FoxgloveConfig(
        host=t.get("host", d.host, str, _nonempty, 'an address to listen on, such as "127.0.0.1"'),
        port=t.get("port", d.port, int, _within(0, 65535), "a TCP port in [0, 65535] (0: any free port)"),
        rate_hz=t.get("rate_hz", d.rate_hz, float, _within(0, MAX_RATE_HZ, True),
                      _range_words("a display rate", 0, MAX_RATE_HZ, "Hz", True)))
    t.finish()
    return foxglove


def _record(t: _ConfigTable) -> RecordConfig:
    from stim300.errors import FormatError
    from stim300.rosimu import check_frame_id

    d = RecordConfig(Path("."))
    directory = Path(t.require("directory", str, _path_text, "a directory path for the recordings"))
    frame_id = t.get("frame_id", d.frame_id, str)
    try:
        check_frame_id(frame_id)
    except FormatError as exc:
        t.fail("frame_id", str(exc).split(": ", 1)[1])
    record = RecordConfig(
        directory=directory,
        rotate_s=t.get("rotate_s", d.rotate_s, float, _within(60, 7 * DAY_S),
                       _range_words("a duration", 60, 7 * DAY_S, "s")),
        rotate_mb=t.get("rotate_mb", d.rotate_mb, float, _within(1, 1 << 20), _range_words("a size", 1, 1 << 20, "MB")),
        keep=t.get("keep", d.keep, int, _within(0, 1 << 20), "a count of files in [0, 1048576] (0: keep all)"),
        frame_id=frame_id)
    t.finish()
    return record


def parse_config(data: dict, where: str) -> DaemonConfig:
    """Build a DaemonConfig from TOML data; `where` names the source in error messages."""
    known = ", ".join(f"[{name}]" for name in sorted(TABLES))
    for key, value in data.items():
        if key not in TABLES and isinstance(value, dict):
            raise ConfigError(f"{where} [{key}]: unknown table (known: {known})")
        if key not in TABLES:
            raise ConfigError(f"{where} {key}: {value!r} is outside the tables; keys belong in one of {known}")
        if not isinstance(value, dict):
            raise ConfigError(f"{where} [{key}]: {value!r} is not a table")

    def table(name: str) -> _ConfigTable:
        return _ConfigTable(data.get(name, {}), f"{where} [{name}]")

    return DaemonConfig(serial=_serial(table("serial")), site=site_from_table(table("site")),
                        state_dir=_state_dir(table("output")), warmup=_warmup(table("warmup")),
                        method=_method(table("method")), detection=_detection(table("detection")),
                        trim=_trim(table("trim")), serve=_serve(table("serve")),
                        ros2=_ros2(table("ros2")) if "ros2" in data else None,
                        foxglove=_foxglove(table("foxglove")) if "foxglove" in data else None,
                        record=_record(table("record")) if "record" in data else None)


def load_config(path: str | Path) -> DaemonConfig:
    """Read and validate the configuration file at `path`; any problem is a one-line ConfigError."""
    where = str(path)
    try:
        text = read_text(path, "TOML configuration file", TEXT_LIMIT_BYTES)
    except UsageError as exc:
        words = str(exc).replace(": no such file", ": no such configuration file")
        raise ConfigError(words) from None
    data = parse_toml(text, where, ConfigError)
    return parse_config(data, where)
