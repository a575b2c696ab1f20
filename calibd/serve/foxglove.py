"""A live view of the daemon in Foxglove: the IMU at a display rate and the calibration (state,
estimates with their 1-sigma, the stream's health, each result) as JSON channels of
foxglove-sdk's WebSocket server (docs/foxglove.md).

`FoxgloveView` is a `calibd.serve.feeds.Feed`: the feeds thread calls it, and must never wait for
a viewer. Every call first asks the SDK whether a client subscribes to its channel and returns at
once when none does, so an unwatched view costs one question per channel; what is logged goes to
per-client queues the SDK bounds (BACKLOG_MESSAGES), dropping a slow client's oldest messages
rather than waiting for it. foxglove-sdk is an optional extra, imported only when a view is made.

A view may also record its channels into an MCAP file (`calibd replay --mcap`): every channel
then has a sink and is logged, each message at the time of the samples it follows, and the file
replaces its path whole when the view closes (`stim300.atomic`).
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec
import numpy as np

from stim300.atomic import atomic_file
from stim300.errors import os_reason
from stim300.protocol import CLUSTERS

from ..correction import uncorrectable
from ..daemon import State
from ..documents import ESTIMATE_BOUNDS, json_value
from .feeds import STREAM_COUNTS, FeedBatch, Health
from .sockets import ServeError

if TYPE_CHECKING:
    from ..results import CalibrationResult

EXTRA_MISSING = "the Foxglove view needs the foxglove extra: pip install 'stim300-calib[foxglove]'"
BACKLOG_MESSAGES = 1024  # messages queued per client; a full queue drops its oldest (the SDK's rule)
VECTORS = ("gyro_deg_h", "acc_mg", "incl_mg")  # the IMU messages' vectors: the sensor's deg/s, g and g shown
_DISPLAY_FACTORS = np.repeat([3600.0, 1000.0, 1000.0], 3)  # deg/h per deg/s, mg per g, mg per g
IMU_TOPICS = {"raw": "/imu/raw", "corrected": "/imu/corrected"}

_NUMBER = {"type": "number"}
_MAYBE_NUMBER = {"type": ["number", "null"]}


def _xyz(unit: str) -> dict:
    return {"type": "object", "description": f"x, y, z in {unit}",
            "properties": {axis: _NUMBER for axis in "xyz"}, "required": list("xyz")}


# topic -> the JSON schema of its messages: what Foxglove's panels offer, and what the layout may name
CHANNELS: dict[str, dict] = {
    **{topic: {
        "title": "calibd.Imu", "type": "object",
        "description": f"{kind} IMU samples averaged over 1/rate_hz; a vector the unit does not measure is absent",
        "properties": {
            "timestamp": {"type": "object", "description": "the mean time of the averaged samples",
                          "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
            "samples": {"type": "integer", "description": "sensor samples in the average"},
            "gyro_deg_h": _xyz("deg/h"), "acc_mg": _xyz("mg"), "incl_mg": _xyz("mg")},
        "required": ["timestamp", "samples", "gyro_deg_h"]} for kind, topic in IMU_TOPICS.items()},
    "/calibd/state": {
        "title": "calibd.State", "type": "object",
        "properties": {"state": {"type": "string", "description": ", ".join(state.value for state in State)},
                       "detail": {"type": "string"},
                       "progress": {"type": "object", "description": "the session's progress (docs/protocol.md)"}},
        "required": ["state", "detail", "progress"]},
    "/calibd/estimates": {
        "title": "calibd.Estimates", "type": "object",
        "description": "each estimate of the latest result; lower and upper are value -/+ sigma",
        "properties": {name: {
            "type": "object", "description": f"in {unit}",
            "properties": {"value": _NUMBER, "sigma": _MAYBE_NUMBER, "lower": _MAYBE_NUMBER, "upper": _MAYBE_NUMBER,
                           "unit": {"type": "string"}, "quality": {"type": ["string", "null"]}}}
            for name, (unit, _) in ESTIMATE_BOUNDS.items()}},
    "/calibd/health": {
        "title": "calibd.Health", "type": "object",
        "description": "the stream's fault counts since the start; flagged_datagrams and faults: since the last",
        "properties": {**{name: {"type": "integer"} for name in (*STREAM_COUNTS, "flagged_datagrams")},
                       "faults": {"type": "array", "items": {"type": "string"},
                                  "description": "the status bits the flagged datagrams set"}}},
    "/calibd/result": {
        "title": "calibd.result", "type": "object", "description": "the result document (docs/result-schema.md)",
        "properties": {"schema": {"type": "string"}, "method": {"type": "string"}, "estimates": {"type": "object"},
                       "warnings": {"type": "array"}}},
}


class FoxgloveView:
    """foxglove-sdk's WebSocket server with calibd's channels, in a context of its own (so views
    share nothing), listening from construction (host None: no server), and the MCAP file
    `mcap` they are recorded into (None: none): a port in use, an MCAP path that cannot be
    written or a missing SDK is a ServeError before the daemon says it is ready."""

    def __init__(self, host: str | None = "127.0.0.1", port: int = 8765, rate_hz: float = 100.0,
                 mcap: Path | None = None):
        try:
            import foxglove
        except ImportError:
            raise ServeError(EXTRA_MISSING) from None
        # the SDK logs each client's reset or failed handshake at ERROR, a line each: any user of
        # the host could fill the daemon's log; what matters to the daemon it raises or says itself
        logging.getLogger("foxglove").setLevel(logging.CRITICAL)
        self._period_ns = max(1, round(1e9 / rate_hz))
        self._open: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # kind -> the samples of its unfinished block
        self._context = foxglove.Context()  # the channels' binding to the server: dropped, it unbinds them
        self._channels = {topic: foxglove.Channel(topic, schema=schema, context=self._context)
                          for topic, schema in CHANNELS.items()}
        self._last_ns: int | None = None  # the newest sample's stamp: the time of what is logged next
        self._server, self._mcap, self._file = None, None, ExitStack()
        try:
            if host is not None:
                self._server = foxglove.start_server(name="calibd", host=host, port=port, context=self._context,
                                                     message_backlog_size=BACKLOG_MESSAGES)
        except RuntimeError as exc:
            self.close()
            why = str(exc).removeprefix("FoxgloveError: ").splitlines()[0]
            address = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
            raise ServeError(f"cannot serve Foxglove on {address}: {why}") from None
        try:
            if mcap is not None:
                self._mcap = foxglove.open_mcap(self._file.enter_context(atomic_file(mcap, durable=False)),
                                                context=self._context)
        except (OSError, RuntimeError) as exc:
            self._file.__exit__(type(exc), exc, exc.__traceback__)  # a temporary file removed, nothing in place
            self.close()
            why = os_reason(exc) if isinstance(exc, OSError) else str(exc).splitlines()[0]
            raise ServeError(f"--mcap {mcap}: cannot write: {why}") from None

    @property
    def port(self) -> int | None:
        """The port listened on (the one the system chose for port 0); None: no server."""
        return None if self._server is None else self._server.port

    def watching(self, topic: str) -> bool:
        """Whether a client subscribes to `topic`: a caller skips work nobody would see."""
        return self._channels[topic].has_sinks()

    def samples(self, batch: FeedBatch) -> None:
        """A batch of reads on /imu/raw, and with its correction taken out (biases, estimated factory
        terms) on /imu/corrected when it has one; nothing for a format whose outputs are not rates
        and accelerations."""
        if len(batch.stamp_ns):
            self._last_ns = int(batch.stamp_ns[-1])
        for kind, correction in (("raw", None), ("corrected", batch.correction)):
            if (kind == "corrected" and correction is None) or not self.watching(IMU_TOPICS[kind]) \
                    or uncorrectable(batch.info.format):
                self._open.pop(kind, None)  # a block is never made of samples a gap lies between
                continue
            columns = np.hstack([batch.samples[c] if correction is None else correction.take_out(c, batch.samples[c])
                                 for c in CLUSTERS], dtype=np.float64)
            self._average(kind, batch.stamp_ns, columns)

    def state(self, state: str, detail: str, progress: dict) -> None:
        """The daemon's state (at each change), its detail and the session's progress record."""
        self._publish("/calibd/state", lambda: {"state": state, "detail": detail, "progress": progress})

    def result(self, result: CalibrationResult) -> None:
        """A result: its estimates flat for plotting, and its whole document."""
        document = functools.cache(result.to_dict)  # made once, and only for a channel watched
        self._publish("/calibd/estimates", lambda: flat_estimates(document()))
        self._publish("/calibd/result", document)

    def health(self, health: Health) -> None:
        """The stream's counts, and the faults the datagrams flagged since the last."""
        self._publish("/calibd/health", lambda: {**health.counts, "flagged_datagrams": health.flagged_datagrams,
                                                 "faults": list(health.faults)})

    def close(self) -> None:
        """Stop listening (clients are disconnected), finish the MCAP file and put it in place,
        and unadvertise the channels."""
        if self._server is not None:
            self._server.stop()
        if self._mcap is not None:
            self._mcap.close()
        self._file.close()
        self._close_channels()

    def _close_channels(self) -> None:
        for channel in self._channels.values():
            channel.close()

    def _average(self, kind: str, stamp_ns: np.ndarray, columns: np.ndarray) -> None:
        """Samples (gyro deg/s, acc g, incl g: nine columns, NaN where the unit measures nothing)
        as block means over 1/rate_hz on /imu/KIND. A block is sent once a later sample shows it
        complete; the rest waits for the next batch."""
        stamps = np.asarray(stamp_ns, np.int64)
        held = self._open.pop(kind, None)
        if held is not None:
            stamps, columns = np.concatenate([held[0], stamps]), np.concatenate([held[1], columns])
        if not len(stamps):
            return
        times, means, counts, rest = block_means(stamps, columns, self._period_ns)
        self._open[kind] = stamps[rest:], columns[rest:]
        means *= _DISPLAY_FACTORS
        channel = self._channels[IMU_TOPICS[kind]]
        for t, row, n in zip(times.tolist(), means.tolist(), counts.tolist()):
            message = {"timestamp": {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000}, "samples": n}
            for i, name in enumerate(VECTORS):
                if row[3 * i] == row[3 * i]:  # NaN: a block this unit's datagrams lack
                    message[name] = dict(zip("xyz", row[3 * i:3 * i + 3]))
            channel.log(msgspec.json.encode(message), log_time=t)

    def _publish(self, topic: str, message: Callable[[], dict]) -> None:
        """`message()` as JSON on `topic`, timed at the newest sample (now before the first: a
        replay faster than real time keeps one time line); not even made when nobody subscribes."""
        channel = self._channels[topic]
        if channel.has_sinks():
            channel.log(msgspec.json.encode(message(), enc_hook=json_value),
                        log_time=time.time_ns() if self._last_ns is None else self._last_ns)


def block_means(stamp_ns: np.ndarray, columns: np.ndarray, period_ns: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Samples cut into blocks by the period their time falls in (a new block wherever it
    changes): each complete block's mean time (ns), column means and sample count, and the index
    where the last block, which later samples may still join, begins."""
    block = stamp_ns // period_ns
    ends = np.flatnonzero(block[1:] != block[:-1]) + 1  # where each block after the first begins
    if not len(ends):
        return np.zeros(0, np.int64), np.zeros((0, columns.shape[1])), np.zeros(0, np.int64), 0
    starts = np.concatenate(([0], ends[:-1]))
    rest = int(ends[-1])
    counts = ends - starts
    first = stamp_ns[starts]
    offsets = np.add.reduceat(stamp_ns[:rest] - np.repeat(first, counts), starts)
    times = first + np.round(offsets / counts).astype(np.int64)
    return times, np.add.reduceat(columns[:rest], starts) / counts[:, None], counts, rest


def flat_estimates(document: dict) -> dict:
    """Each estimate of a result document as {value, sigma, lower, upper, unit, quality}, so a
    plot can draw value with its 1-sigma band (lower and upper are None without a sigma)."""
    flat = {}
    for name, estimate in document.get("estimates", {}).items():
        value, sigma = estimate["value"], estimate.get("sigma")
        flat[name] = {"value": value, "sigma": sigma, "lower": None if sigma is None else value - sigma,
                      "upper": None if sigma is None else value + sigma, "unit": estimate["unit"],
                      "quality": estimate.get("quality")}
    return flat
