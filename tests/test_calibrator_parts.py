"""The daemon's collaborators, each alone: the solve trigger on synthetic gyro data, the collector
and the restart cuts across a sensor restart, the warm-up watch on a synthetic temperature, one
solve, and the listeners hearing a fixture replay."""

import json
from pathlib import Path

import numpy as np
import pytest

from calibd.captures import load_session
from calibd.config import MethodConfig, WarmupConfig
from calibd.daemon import Calibrator, Listener, State, StateLog, stale_result
from calibd.daemon import collector as collector_module
from calibd.daemon.collector import Collector
from calibd.daemon.solver import solve
from calibd.daemon.trigger import SolveTrigger
from calibd.daemon.warmwatch import WARM_CHECK_EVERY_S, WarmWatch
from calibd.frames import Site
from calibd.live import configure_logging, replay
from calibd.methods import estimator
from calibd.results import ResultStream
from calibd.statedir import ResultStore
from calibd.segments import session_segments
from calibd.session import PowerUpCuts, SessionBuilder
from calibd.units import value_sigma
from calibd.warmup import settling
from stim300.bulk import decode_capture
from stim300.codec import SAMPLE_DTYPE
from stim300.source import CaptureSource
from stim300.records import SensorRecord

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
HEADING137 = FIXTURES / "heading137_lat60_125hz.bin"
FAULTS = FIXTURES / "faults_125hz.bin"  # a sensor restart at sample 4986 (about 40 s)
RATE_HZ = 125
SETTINGS = {"turn_threshold_deg_s": None, "smooth_s": 0.2, "settle_s": 1.0, "min_static_s": 5.0}


# ---- the trigger ----------------------------------------------------------------------------

def quiet_turn_quiet(turn_start_s=10.0, turn_s=4.5, rate_deg_s=20.0, total_s=30.0, seed=3):
    """Gyro (deg/s) of a platform at rest, turning about z at `rate_deg_s`, at rest again."""
    t = np.arange(round(total_s * RATE_HZ)) / RATE_HZ
    gyro = np.random.default_rng(seed).normal(0.0, 0.01, (len(t), 3))
    gyro[(t >= turn_start_s) & (t < turn_start_s + turn_s), 2] += rate_deg_s
    return t, gyro


def first_stop_s(trigger, t, gyro, batch=25):
    """Data time of the end of the first batch after which the trigger sees the platform stopped."""
    for start in range(0, len(t), batch):
        now_s = float(t[min(start + batch, len(t)) - 1])
        if trigger.stopped_moving(t[start:start + batch], gyro[start:start + batch], now_s, SETTINGS, RATE_HZ):
            return now_s
    return None


def test_the_trigger_fires_once_the_platform_has_been_quiet_for_settle_and_minimum_static():
    t, gyro = quiet_turn_quiet()
    stop_s = first_stop_s(SolveTrigger(), t, gyro)
    turn_end_s = 10.0 + 4.5
    quiet_needed_s = SETTINGS["settle_s"] + SETTINGS["min_static_s"]
    assert turn_end_s + quiet_needed_s - 0.2 <= stop_s <= turn_end_s + quiet_needed_s + 25 / RATE_HZ + 0.2


def test_the_trigger_stays_silent_without_motion_and_below_the_threshold_floor():
    t, gyro = quiet_turn_quiet(rate_deg_s=0.3)  # below the 0.5 deg/s floor before the tracker's first update
    assert first_stop_s(SolveTrigger(), t, gyro) is None
    assert first_stop_s(SolveTrigger(), t, quiet_turn_quiet(rate_deg_s=0.0)[1]) is None


def test_the_trigger_is_cleared_by_a_look_that_ends_on_a_static_only():
    t, gyro = quiet_turn_quiet()
    trigger = SolveTrigger()
    assert first_stop_s(trigger, t, gyro) is not None
    session = load_session(str(HEADING137))
    segments = session_segments(session)
    turn = next(k for k, s in enumerate(segments) if s.kind == "turn")
    assert not trigger.campaign_done(segments[:turn + 1], estimator("joint"))  # ends on a turn: look again later
    assert trigger.stopped_moving(t[:0], gyro[:0], float(t[-1]), SETTINGS, RATE_HZ)
    assert trigger.campaign_done(segments[:turn + 2], estimator("joint"))  # a static after the turn: complete
    assert not trigger.stopped_moving(t[:0], gyro[:0], float(t[-1]), SETTINGS, RATE_HZ)


def test_the_re_solve_timer_counts_data_time_from_the_last_attempt():
    trigger = SolveTrigger()
    trigger.session_started(100.0, 30.0)
    assert not trigger.timer_due(129.9) and trigger.timer_due(130.0)
    trigger.solved(140.0, 30.0)
    assert not trigger.timer_due(169.9) and trigger.timer_due(170.0)
    assert not trigger.unsolved(140.0) and trigger.unsolved(140.1)


# ---- the collector across a restart ---------------------------------------------------------

def collect(samples, restarts_at_batch=None, batch=25):
    """Feed `samples` through PowerUpCuts into collectors as the Calibrator does: a new Collector
    at every restart; `restarts_at_batch`: the parser saw a restart's power-up datagrams before
    that sample. Returns the collectors and the sample numbers where each new power-up began."""
    cuts, collectors, cut_at = PowerUpCuts(), [Collector()], []
    restart_datagrams = () if restarts_at_batch is None else (restarts_at_batch,)
    for start in range(0, len(samples), batch):
        fed = start
        for restarted, piece in cuts.pieces(samples[start:start + batch], start, restart_datagrams):
            if restarted:
                collectors.append(Collector())
                cut_at.append(fed)
            if len(piece):
                collectors[-1].store(piece, collectors[-1].times(piece, RATE_HZ))
            fed += len(piece)
    return collectors, cut_at


def test_the_start_up_bit_alone_cuts_the_stream_at_the_restarts_first_sample():
    decoded = decode_capture(FAULTS.read_bytes())
    samples, restart_at = decoded.samples, decoded.info.stats.restart_datagrams[0]
    (first, second), cut_at = collect(samples)
    assert cut_at == [restart_at]
    lost = decoded.info.stats.lost_samples
    assert (restart_at - 1) / RATE_HZ <= first.end_s <= (restart_at - 1 + lost) / RATE_HZ
    second_times = second.data.arrays()["time_s"]
    assert second_times[0] == 0.0 and np.all(np.diff(second_times) > 0)  # its own counter clock from power-up
    assert second.end_s == pytest.approx((len(samples) - restart_at - 1) / RATE_HZ, abs=(lost + 1) / RATE_HZ)


def test_a_counted_restart_is_one_cut_even_when_the_new_power_up_starts_with_its_start_up_bit():
    decoded = decode_capture(FAULTS.read_bytes())
    samples, restart_at = decoded.samples, decoded.info.stats.restart_datagrams[0]
    batch_start = restart_at // 25 * 25
    collectors, cut_at = collect(samples[:batch_start].copy(), None)
    assert len(collectors) == 1  # the first power-up alone: no cut
    _, cut_at = collect(np.concatenate([samples[:batch_start], samples[restart_at:]]), batch_start)
    assert cut_at == [batch_start]


def test_the_collectors_session_starts_where_asked_and_stops_growing_at_the_bound(monkeypatch):
    from calibd.config import DetectionConfig

    samples = decode_capture(HEADING137.read_bytes()).samples
    collector = Collector()
    collector.store(samples[:2500], collector.times(samples[:2500], RATE_HZ))  # 20 s
    collector.start_session(10.0, DetectionConfig())
    session = collector.session(SensorRecord(serial_number="N1"), ResultStream(capture="x.bin", session=3))
    assert session.time_s[0] == 0.0 and session.time_s[-1] == pytest.approx(20.0 - 1 / RATE_HZ - 10.0, abs=0.2)
    assert session.stream == ResultStream(capture="x.bin", session=3, flagged_datagrams=0, fault_flags=())
    assert session.stream.hidden_gaps is None  # no host times: none looked for
    assert [s.kind for s in collector.segments(session)] == ["static"]
    monkeypatch.setattr(collector_module, "MAX_SESSION_S", 15.0)
    assert collector.store(samples[2500:3125], collector.times(samples[2500:3125], RATE_HZ)) is not None  # to 25 s
    end_s = collector.end_s
    assert collector.store(samples[3125:3250], collector.times(samples[3125:3250], RATE_HZ)) is None  # beyond 15 s
    assert collector.end_s == end_s


# ---- the warm-up watch ----------------------------------------------------------------------

def warming_samples(duration_s, temperature=True):
    """A sensor at rest whose temperature rises 10 degC with a 100 s time constant."""
    t = np.arange(round(duration_s * RATE_HZ)) / RATE_HZ
    s = np.zeros(len(t), SAMPLE_DTYPE)
    for name in ("temp_gyro", "temp_acc", "temp_incl"):
        s[name] = (30.0 + 10.0 * (1 - np.exp(-t / 100.0)))[:, None] if temperature else np.nan
    return t, s


def watch(t, s, rule):
    """Feed 1-s batches; the first verdict with a start, and every detail said before it."""
    data, warm, details = SessionBuilder(), WarmWatch(), []
    for start in range(0, len(t), RATE_HZ):
        data.add(s[start:start + RATE_HZ], t[start:start + RATE_HZ], RATE_HZ)
        verdict = warm.look(data, rule)
        if verdict is not None and verdict.start_s is not None:
            return verdict, details
        if verdict is not None:
            details.append(verdict.detail)
    return None, details


def test_the_warm_watch_starts_the_session_where_the_rule_does_on_the_whole_record():
    rule = WarmupConfig(window_s=100.0)
    t, s = warming_samples(900.0)
    verdict, details = watch(t, s, rule)
    reference = settling(t, np.nanmean(s["temp_gyro"], axis=1), rule)
    assert reference.settled and abs(verdict.start_s - reference.start_s) <= 1.0
    assert verdict.detail.startswith("warmed up (+") and verdict.detail.endswith("degC/h over 100 s)")
    assert details[0] == "warming up: 1 s since power-up"  # the first look, at the first batch's end
    assert "temperature moving" in details[-1]
    assert len(details) == pytest.approx((verdict.start_s + 100.0) / WARM_CHECK_EVERY_S, abs=2)  # a look per 10 s


def test_without_temperatures_the_watch_waits_the_window_since_power_up():
    t, s = warming_samples(200.0, temperature=False)
    verdict, _ = watch(t, s, WarmupConfig(window_s=100.0))
    assert verdict.start_s == 0.0 and "no temperatures in the datagram" in verdict.detail


# ---- one solve ------------------------------------------------------------------------------

@pytest.mark.slow
def test_a_solve_says_what_the_campaign_lacks_or_gives_the_result_with_its_session_record():
    session = load_session(str(HEADING137))
    segments = session_segments(session)
    lacking = solve(session, segments[:1], Site(60.0), MethodConfig(), estimator("joint").options({}), 4)
    assert lacking.result is None and not lacking.failed
    assert lacking.detail.endswith(", 1 static at 0/4 index headings, 0 index turns, 0 full turns, 0 other turns; "
                                   "waiting for: a turn and a static after it on the level static's mounting (+Z up)")
    assert lacking.progress.fields()["missing"] == lacking.detail.split("waiting for: ")[1]
    solved = solve(session, segments, Site(60.0), MethodConfig(), estimator("joint").options({}), 4)
    assert solved.result.session.number == 4
    assert solved.result.session.duration_s == pytest.approx(float(session.time_s[-1]))
    yaw = solved.result.estimates["yaw"]
    assert solved.detail == (f"solved on {session.time_s[-1]:.0f} s: yaw {value_sigma(yaw.value, yaw.sigma, 'deg')}; "
                             f"{solved.progress.found()}; campaign complete")
    assert solved.progress.complete and solved.progress.fields()["missing"] is None
    stale = stale_result(solved.result, "why")
    assert stale.stale.reason == "why" and stale.warnings[0] == "stale: why"
    assert solved.result.stale is None  # a copy: the result itself is unchanged


# ---- the listeners --------------------------------------------------------------------------

class Recorder(Listener):
    """Hears states and results only: the protocol's other methods do nothing."""

    def __init__(self):
        self.states, self.results = [], []

    def on_state(self, state, detail, progress=None):
        self.states.append(state)

    def on_result(self, result):
        self.results.append(result)


@pytest.mark.slow
def test_listeners_hear_the_state_sequence_of_a_fixture_replay_in_their_order(tmp_path):
    from structlog.testing import capture_logs

    configure_logging()  # info level: the state log's events are seen
    recorder, store = Recorder(), ResultStore(tmp_path, {"capture": "heading137"})
    calibrator = Calibrator(Site(60.0), WarmupConfig(window_s=10.0), MethodConfig(resolve_every_s=1e9),
                            listeners=[StateLog(), recorder, store])
    with capture_logs() as logs:
        replay(CaptureSource(HEADING137.read_bytes()), calibrator)
    changes = [s for k, s in enumerate(recorder.states) if k == 0 or s != recorder.states[k - 1]]
    assert changes == [State.WARMING_UP, State.COLLECTING, State.SOLVED]
    assert [e["state"] for e in logs if e["event"] == "state"] == [s.value for s in changes]
    assert len([e for e in logs if e["event"] == "solved"]) == len(recorder.results) >= 1
    assert recorder.results[-1] is calibrator.result
    state = json.loads((tmp_path / "state.json").read_text())
    assert state["state"] == "SOLVED" and state["capture"] == "heading137" and state["detail"] == calibrator.detail
    from calibd.cli import _status  # what `calibd status` prints: the progress record's words, complete once solved
    record = calibrator.progress
    assert record.complete and f"; {record.found()}; campaign complete), updated " in _status(tmp_path, False)
    assert calibrator.progress_fields() | record.fields() == calibrator.progress_fields()  # STATE's progress
    written = json.loads((tmp_path / "result.json").read_text())
    assert written["estimates"]["yaw"]["value"] == calibrator.result.estimates["yaw"].value
    assert len(list((tmp_path / "history").iterdir())) == len(recorder.results)
    stream = written["stream"]  # the stream's statistics, as an offline result has them
    decoded = decode_capture(HEADING137.read_bytes()).info.stats
    assert (stream["datagrams"], stream["lost_samples"], stream["crc_errors"]) == (
        decoded.datagrams, decoded.lost_samples, decoded.crc_errors)
    assert {"inferred_missing", "restarts", "warnings"} <= set(stream) and stream["session"] == 1


def test_systemds_status_line_is_a_listener(monkeypatch):
    import socket
    import tempfile

    from calibd.live import SystemdStatus

    with tempfile.TemporaryDirectory(dir="/tmp") as directory, \
            socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify:
        notify.bind(f"{directory}/notify")
        monkeypatch.setenv("NOTIFY_SOCKET", f"{directory}/notify")
        SystemdStatus().on_state(State.COLLECTING, "collecting: 12 s of data")
        notify.settimeout(5.0)
        assert notify.recv(256) == b"STATUS=collecting: collecting: 12 s of data"
