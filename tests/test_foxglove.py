"""The Foxglove view (calibd.serve.foxglove), fed as the feeds thread feeds it, against a Foxglove
WebSocket protocol client written here: what each channel carries, decoded; the layout's message
paths against the channels' schemas; its errors; nothing done while nobody watches."""

import json
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from websockets.sync.client import connect  # the test client's WebSocket (the test extra has it)

from calibd.correction import ServedCorrection
from calibd.documents import json_value
from calibd.results import CalibrationResult, Estimate
from calibd.serve import foxglove as view_module
from calibd.serve.feeds import FeedBatch, Health
from calibd.serve.foxglove import CHANNELS, EXTRA_MISSING, FoxgloveView
from calibd.serve.sockets import ServeError
from stim300.capture import stream_info
from stim300.codec import SAMPLE_DTYPE
from stim300.protocol import GyroUnit
from stim300.special import Configuration, encode_special
from stim300.stream import StreamParser

LAYOUT = Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json"
# the protocol's name since foxglove-sdk 0.9 (the same messages as foxglove.websocket.v1, which it refuses)
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 1  # the opcode of a binary MessageData frame
T0_NS = 1_800_000_000_000_000_000  # a whole 10 ms: blocks at 100 Hz start with the first sample


class Client:
    """A Foxglove WebSocket client: serverInfo and advertise on connecting, subscribe, and binary
    MessageData frames (opcode, subscription id, log time, payload) decoded as JSON."""

    def __init__(self, port: int):
        self._connection = connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=5)
        self.ws = self._connection.__enter__()
        info = json.loads(self.ws.recv(timeout=5))
        assert info["op"] == "serverInfo" and info["name"] == "calibd"
        self.channels: dict[str, dict] = {}
        self.advertised = 0  # channels advertised, counted apart: a topic advertised twice shows
        while len(self.channels) < len(CHANNELS):
            self._take(self.ws.recv(timeout=5))
        self.topics: dict[int, str] = {}  # subscription id -> topic

    def subscribe(self, view: FoxgloveView, *topics: str) -> None:
        """Subscribe to `topics` and wait until the view knows (it drops what nobody watches)."""
        first = len(self.topics)
        subscriptions = [{"id": first + i, "channelId": self.channels[topic]["id"]} for i, topic in enumerate(topics)]
        self.topics |= {s["id"]: topic for s, topic in zip(subscriptions, topics)}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))
        deadline = time.monotonic() + 5
        while not all(view.watching(topic) for topic in topics):
            assert time.monotonic() < deadline, "the subscription never reached the view"
            time.sleep(0.005)

    def receive(self, timeout: float = 5.0) -> tuple[str, int, dict]:
        """The next MessageData: (topic, log time in ns, the JSON payload)."""
        while (data := self._take(self.ws.recv(timeout=timeout))) is None:
            pass
        return data

    def _take(self, frame: str | bytes) -> tuple[str, int, dict] | None:
        """A binary MessageData frame decoded; a text frame's advertised channels noted."""
        if isinstance(frame, bytes):
            assert frame[0] == MESSAGE_DATA
            subscription, log_time = struct.unpack_from("<IQ", frame, 1)
            return self.topics[subscription], log_time, json.loads(frame[13:])
        message = json.loads(frame)
        if message["op"] == "advertise":
            self.channels |= {channel["topic"]: channel for channel in message["channels"]}
            self.advertised += len(message["channels"])
        return None

    def nothing_more(self) -> bool:
        try:
            self.receive(timeout=0.2)
        except TimeoutError:
            return True
        return False

    def close(self) -> None:
        self._connection.__exit__(None, None, None)


@pytest.fixture
def view():
    made = FoxgloveView(port=0)
    yield made
    made.close()


@pytest.fixture
def client(view):
    made = Client(view.port)
    yield made
    made.close()


def stream(**configuration):
    """The StreamInfo of a 2000 Hz unit configured so (rate, acceleration, inclination by default)."""
    parser = StreamParser()
    parser.feed(encode_special(Configuration.build(sample_rate_hz=2000, **configuration), crlf=False))
    return stream_info(parser)


RATES = stream()
RESULT = CalibrationResult(method="joint", site={"latitude_deg": 59.9}, estimates={
    "yaw": Estimate(12.5, 0.25, "deg"), "gyro_bias_x": Estimate(0.75, None, "deg/h", "poor"),
    "acc_bias_z": Estimate(-1.5, 0.125, "mg")})


def batch(n: int, rate_hz: float = 2000.0, incl: bool = True, correction=None, info=RATES, seed: int = 1):
    """`n` samples at `rate_hz` from T0_NS as the feeds thread hands them over (gyro deg/s, acc
    and incl g; incl NaN, as decoded, for a unit without inclinometers)."""
    rng = np.random.default_rng(seed)
    samples = np.zeros(n, SAMPLE_DTYPE)
    samples["gyro"] = rng.normal(0, 0.01, (n, 3))
    samples["acc"] = rng.normal(0, 0.001, (n, 3)) + [0, 0, 1]
    samples["incl"] = rng.normal(0, 0.001, (n, 3)) + [0, 0, 1] if incl else np.nan
    stamps = T0_NS + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    return FeedBatch(samples, stamps, correction, info)


def part(whole: FeedBatch, rows: slice) -> FeedBatch:
    return FeedBatch(whole.samples[rows], whole.stamp_ns[rows], whole.correction, whole.info)


def block_mean(values: np.ndarray, rows: slice, factor: float) -> list[float]:
    return (values[rows].astype(np.float64).mean(axis=0) * factor).tolist()


def test_the_imu_is_sent_as_block_means_at_the_display_rate_with_units_in_the_names(view, client):
    client.subscribe(view, "/imu/raw")
    whole = batch(201)  # 10 blocks of 20 at 100 Hz, and one sample that ends the tenth
    view.samples(part(whole, slice(0, 30)))  # a block cut between two batches
    view.samples(part(whole, slice(30, None)))
    stamps, samples = whole.stamp_ns, whole.samples
    for block in range(10):
        rows = slice(20 * block, 20 * block + 20)
        topic, log_time, message = client.receive()
        mean_ns = int(stamps[rows][0]) + round(float((stamps[rows] - stamps[rows][0]).mean()))
        assert topic == "/imu/raw" and message["samples"] == 20
        assert log_time == mean_ns == message["timestamp"]["sec"] * 10**9 + message["timestamp"]["nsec"]
        for field, cluster, factor in (("gyro_deg_h", "gyro", 3600), ("acc_mg", "acc", 1000),
                                       ("incl_mg", "incl", 1000)):
            expected = block_mean(samples[cluster], rows, factor)
            assert [message[field][a] for a in "xyz"] == pytest.approx(expected, rel=1e-12, abs=1e-12)
    assert client.nothing_more()  # the 201st sample's block is not complete


def test_corrected_carries_the_samples_less_the_biases_only_with_a_correction(view, client):
    client.subscribe(view, "/imu/corrected")
    view.samples(batch(41))  # no correction (no result yet, or a format that takes none)
    assert client.nothing_more()
    bias = {"gyro": np.array([0.01, -0.02, 0.005], np.float32), "acc": np.array([0.001, 0, -0.002], np.float32)}
    corrected = batch(41, incl=False, correction=ServedCorrection(RESULT, bias), seed=2)
    view.samples(corrected)
    for block in range(2):
        rows = slice(20 * block, 20 * block + 20)
        topic, _, message = client.receive()
        assert topic == "/imu/corrected" and set(message) == {"timestamp", "samples", "gyro_deg_h", "acc_mg"}
        for field, cluster, factor in (("gyro_deg_h", "gyro", 3600), ("acc_mg", "acc", 1000)):
            expected = block_mean(corrected.samples[cluster] - bias[cluster], rows, factor)
            assert [message[field][a] for a in "xyz"] == pytest.approx(expected, rel=1e-9, abs=1e-9)
    assert client.nothing_more()


def test_outputs_that_are_not_rates_send_no_imu(view, client):
    client.subscribe(view, "/imu/raw")
    view.samples(batch(41, info=stream(gyro_unit=GyroUnit.INCREMENTAL_ANGLE)))
    assert client.nothing_more()


def test_a_sensor_slower_than_the_display_rate_is_sent_sample_by_sample(view, client):
    client.subscribe(view, "/imu/raw")
    slow = batch(4, rate_hz=50.0)
    view.samples(slow)
    received = [client.receive() for _ in range(3)]
    assert [log_time for _, log_time, _ in received] == slow.stamp_ns[:3].tolist()
    assert [m["gyro_deg_h"]["z"] for _, _, m in received] == pytest.approx(slow.samples["gyro"][:3, 2] * 3600.0)


def test_state_estimates_health_and_result_reach_their_channels(view, client):
    client.subscribe(view, "/calibd/state", "/calibd/estimates", "/calibd/health", "/calibd/result")
    view.state("COLLECTING", "2 of 4 headings", {"warmed_up": True, "statics": 2})
    view.result(RESULT)
    view.health(Health("COLLECTING", "", {"crc_errors": 3, "lost_samples": 0, "hidden_gaps": 1}, 2, ("gyro x",)))
    received = {topic: message for topic, _, message in (client.receive() for _ in range(4))}
    assert received["/calibd/state"] == {"state": "COLLECTING", "detail": "2 of 4 headings",
                                         "progress": {"warmed_up": True, "statics": 2}}
    assert received["/calibd/estimates"] == {
        "yaw": {"value": 12.5, "sigma": 0.25, "lower": 12.25, "upper": 12.75, "unit": "deg", "quality": None},
        "gyro_bias_x": {"value": 0.75, "sigma": None, "lower": None, "upper": None, "unit": "deg/h",
                        "quality": "poor"},
        "acc_bias_z": {"value": -1.5, "sigma": 0.125, "lower": -1.625, "upper": -1.375, "unit": "mg",
                       "quality": None}}
    assert received["/calibd/health"] == {"crc_errors": 3, "lost_samples": 0, "hidden_gaps": 1,
                                          "flagged_datagrams": 2, "faults": ["gyro x"]}
    assert received["/calibd/result"] == json.loads(json.dumps(RESULT.to_dict(), default=json_value))


def test_every_channel_is_advertised_as_json_with_its_schema(view, client):
    assert set(client.channels) == set(CHANNELS)
    for topic, channel in client.channels.items():
        assert channel["encoding"] == "json" and channel["schemaEncoding"] == "jsonschema"
        assert json.loads(channel["schema"]) == CHANNELS[topic]


def test_nothing_is_done_while_nobody_watches(view, monkeypatch):
    calls = []
    for owner, name in ((view_module, "block_means"), (view_module, "flat_estimates"), (CalibrationResult, "to_dict")):
        monkeypatch.setattr(owner, name, lambda *args, name=name, real=getattr(owner, name):
                            calls.append(name) or real(*args))
    corrected = batch(100, correction=ServedCorrection(RESULT, {"gyro": np.ones(3, np.float32)}))
    view.samples(corrected)
    view.result(RESULT)
    assert calls == []
    watcher = Client(view.port)
    try:  # connected and watching, the same calls work, the document made once for both channels
        watcher.subscribe(view, "/imu/raw", "/imu/corrected", "/calibd/estimates", "/calibd/result")
        view.samples(corrected)
        view.result(RESULT)
        assert sorted(calls) == ["block_means", "block_means", "flat_estimates", "to_dict"]
    finally:
        watcher.close()


def test_a_client_that_stops_reading_never_holds_the_caller_and_loses_its_oldest(view):
    stalled = Client(view.port)
    try:
        stalled.subscribe(view, "/calibd/state")
        details = [f"step {i}" for i in range(5000)]  # 25 MB: beyond the socket buffers and the SDK's queue
        caller = threading.Thread(target=lambda: [view.state("COLLECTING", d, {"pad": "x" * 5000}) for d in details])
        caller.start()
        caller.join(timeout=20)
        assert not caller.is_alive()
        received = []
        while not received or received[-1] != details[-1]:  # the newest is kept
            received.append(stalled.receive()[2]["detail"])
        assert len(received) < len(details)
        assert received == sorted(received, key=details.index)  # in order, with the oldest dropped
    finally:
        stalled.close()


def test_clients_that_reset_or_speak_garbage_leave_nothing_in_the_log(view, caplog):
    rude = Client(view.port)
    rude.ws.socket.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    rude.ws.socket.close()  # a reset, no closing handshake
    with socket.create_connection(("127.0.0.1", view.port)) as rogue:
        rogue.sendall(b"GET / HTTP/1.1\r\nHost: calibd\r\n\r\n" + bytes(range(256)))
        rogue.recv(4096)
    watcher = Client(view.port)  # served as ever
    try:
        watcher.subscribe(view, "/calibd/state")
        view.state("SOLVED", "", {})
        assert watcher.receive()[2]["state"] == "SOLVED"
    finally:
        watcher.close()
    assert [r.getMessage() for r in caplog.records if r.name.startswith("foxglove")] == []


def test_views_in_one_process_share_nothing(view):
    other = FoxgloveView(port=0)
    watcher = Client(view.port)
    try:
        assert other.port != view.port
        watcher.subscribe(view, "/calibd/state")
        assert not other.watching("/calibd/state")
        other.state("SOLVED", "from the other view", {})
        view.state("SOLVED", "from this view", {})
        assert watcher.receive()[2]["detail"] == "from this view"
        assert watcher.nothing_more() and watcher.advertised == len(CHANNELS)  # this view's channels only
    finally:
        watcher.close()
        other.close()


def test_a_port_in_use_is_one_line_naming_the_address():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ServeError) as error:
            FoxgloveView(port=port)
    message = str(error.value)
    assert f"127.0.0.1:{port}" in message and "\n" not in message and "in use" in message


def test_the_sdk_missing_is_one_line_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove raises ImportError
    with pytest.raises(ServeError) as error:
        FoxgloveView(port=0)
    assert str(error.value) == EXTRA_MISSING


def test_importing_calibd_and_the_view_loads_no_foxglove():
    code = "import sys, calibd, calibd.serve, calibd.serve.foxglove; print('foxglove' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"


def message_paths(node):
    """Every message path a layout's panels read: plot and state-transition series, raw messages."""
    if isinstance(node, dict):
        for key, value in node.items():
            if key in ("value", "topicPath") and isinstance(value, str) and value.startswith("/"):
                yield value
            else:
                yield from message_paths(value)
    elif isinstance(node, list):
        for item in node:
            yield from message_paths(item)


def schema_has(schema: dict, fields: list[str]) -> bool:
    for field in fields:
        schema = schema.get("properties", {}).get(field)
        if schema is None:
            return False
    return True


def test_the_layout_names_only_channels_and_fields_that_exist():
    layout = json.loads(LAYOUT.read_text())
    paths = set(message_paths(layout["configById"]))
    for path in paths:
        topic, *fields = path.split(".")
        assert topic in CHANNELS, path
        assert schema_has(CHANNELS[topic], fields), path
    assert {"/imu/raw.gyro_deg_h.x", "/imu/raw.gyro_deg_h.y", "/imu/raw.acc_mg.x", "/imu/raw.acc_mg.y",
            "/imu/raw.incl_mg.x", "/imu/raw.incl_mg.y", "/calibd/estimates.yaw.value", "/calibd/estimates.yaw.lower",
            "/calibd/estimates.yaw.upper", "/calibd/state.state"} <= paths
    panels = layout["configById"]
    assert set(panels) == set(mosaic_leaves(layout["layout"]))  # every panel placed, none missing


def mosaic_leaves(node):
    if isinstance(node, str):
        yield node
    else:
        yield from mosaic_leaves(node["first"])
        yield from mosaic_leaves(node["second"])


def test_an_estimates_schema_field_exists_for_every_estimate_name_and_a_wrong_path_is_caught():
    assert schema_has(CHANNELS["/calibd/estimates"], ["pitch", "upper"])
    assert not schema_has(CHANNELS["/calibd/estimates"], ["heading", "value"])
    assert not schema_has(CHANNELS["/imu/raw"], ["gyro", "x"])


def test_a_port_in_use_ends_a_served_replay_before_it_starts_with_one_line(tmp_path):
    """Through the daemon's own start: the [foxglove] table's port taken -> one line, nothing served."""
    from captures import command_env

    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    config = tmp_path / "calibd.toml"
    config.write_text(f'[serial]\nport = "{tmp_path}/tty"\n[site]\nlatitude_deg = 40\n[output]\n'
                      f'state_dir = "{tmp_path}/state"\n[foxglove]\nport = {port}\n')
    capture = Path(__file__).resolve().parents[1] / "fixtures" / "faults_125hz.bin"
    done = subprocess.run([sys.executable, "-m", "calibd.cli", "replay", str(capture), "--config", str(config),
                           "--serve"], capture_output=True, text=True, env=command_env(), timeout=60)
    taken.close()
    assert done.returncode == 1 and done.stdout == "", done.stdout
    assert done.stderr.count("\n") == 1 and f"cannot serve Foxglove on 127.0.0.1:{port}" in done.stderr, done.stderr


def recorded_view(path: Path) -> list[tuple[str, int, dict]]:
    """An MCAP file's messages: (topic, log time in ns, the JSON payload), in the file's order."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(channel.topic, message.log_time, json.loads(message.data))
                for _, channel, message in make_reader(f).iter_messages(log_time_order=False)]


def test_a_view_recorded_to_mcap_logs_every_channel_on_the_samples_time_line(tmp_path):
    """Without a server and without a client: the MCAP file is every channel's sink. What comes
    after samples is logged at the newest sample's time (a replay faster than real time keeps one
    time line), what comes before at the host's; the file is put in place whole at close."""
    path = tmp_path / "view.mcap"
    view = FoxgloveView(host=None, mcap=path)
    assert view.port is None
    before = time.time_ns()
    view.state("WARMING_UP", "waiting", {})
    whole = batch(201)
    view.samples(whole)
    view.result(RESULT)
    view.health(Health("COLLECTING", "", {"crc_errors": 0}, 0, ()))
    assert not path.exists()
    view.close()
    got = recorded_view(path)
    assert [topic for topic, _, _ in got] == ["/calibd/state", *["/imu/raw"] * 10, "/calibd/estimates",
                                              "/calibd/result", "/calibd/health"]
    assert before <= got[0][1] <= time.time_ns()
    assert [t for topic, t, _ in got[11:]] == [int(whole.stamp_ns[-1])] * 3
    assert got[12][2] == json.loads(json.dumps(RESULT.to_dict(), default=json_value))
    raw_times = [t for topic, t, _ in got if topic == "/imu/raw"]
    assert raw_times == sorted(raw_times) and raw_times[0] >= T0_NS
    assert list(tmp_path.iterdir()) == [path]  # no temporary file beside it


def test_an_mcap_path_that_cannot_be_written_is_one_line_and_leaves_nothing(tmp_path):
    missing = tmp_path / "missing" / "view.mcap"
    with pytest.raises(ServeError) as refused:
        FoxgloveView(host=None, mcap=missing)
    assert str(refused.value).startswith(f"--mcap {missing}: ") and "\n" not in str(refused.value)
    (tmp_path / "dir.mcap").mkdir()
    with pytest.raises(ServeError, match="dir.mcap"):
        FoxgloveView(host=None, mcap=tmp_path / "dir.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.mcap"]


HEADING137 = Path(__file__).resolve().parents[1] / "fixtures" / "heading137_lat60_125hz.bin"


@pytest.mark.slow
def test_replay_records_the_view_of_a_calibration_into_mcap(tmp_path, run_main):
    """`calibd replay --mcap` at full speed, through the daemon's own port reader and feeds: the
    capture's IMU at the display rate on the sensor's time line, the states it went through, and
    the result as the state directory holds it."""
    from calibd.cli import main as calibd_main

    view = tmp_path / "view.mcap"
    code, out, err = run_main(calibd_main, ["replay", str(HEADING137), "--latitude", "60", "--mcap", str(view),
                                            "--state-dir", str(tmp_path / "state"), "--warmup-window", "300"])
    assert code == 0, err
    got = recorded_view(view)
    raw = [t for topic, t, _ in got if topic == "/imu/raw"]
    seconds = len(HEADING137.read_bytes()) / 125 / 50  # roughly: 125 Hz datagrams of about 50 bytes
    assert raw == sorted(raw) and 0.5 * seconds < (raw[-1] - raw[0]) / 1e9 < 2 * seconds
    assert 90 < len(raw) / ((raw[-1] - raw[0]) / 1e9) <= 101  # blocks of 10 ms
    states = [message["state"] for topic, _, message in got if topic == "/calibd/state"]
    assert "SOLVED" in states or "MONITORING" in states, states
    results = [message for topic, _, message in got if topic == "/calibd/result"]
    assert results[-1] == json.loads((tmp_path / "state" / "result.json").read_text())


def test_replay_refuses_an_mcap_view_not_named_mcap_or_naming_its_capture(tmp_path, run_main):
    from calibd.cli import main as calibd_main

    link = tmp_path / "capture.mcap"
    link.symlink_to(HEADING137)
    for given, words in ((tmp_path / "view.json", "name it .mcap"), (link, "would destroy the input")):
        code, out, err = run_main(calibd_main, ["replay", str(HEADING137), "--latitude", "60", "--mcap", str(given)])
        assert code == 2 and words in err and err.count("\n") == 1, err
