"""The estimator seam: the registry names the methods, each says what a partial session still
lacks (None once it holds the campaign) and solves through one call; the daemon, `calibd
calibrate` and the configuration find methods there."""

import dataclasses
import tomllib
from pathlib import Path

import pytest

from calibd import config
from calibd.captures import load_session
from calibd.segments import session_segments
from calibd.config import ConfigError, MethodConfig, WarmupConfig, parse_config
from calibd.daemon import Calibrator, Callbacks
from calibd.methods import (DAEMON_METHODS, ESTIMATORS, CampaignIncomplete, JointOptions, OptionError,
                            ThesisOptions, estimator)
from calibd.frames import Site
from calibd.results import CalibrationResult
from stim300.bulk import decode_capture

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
SITE = Site(40.59129, g0=9.79956)


@pytest.fixture(scope="module")
def sessions():
    """name -> (session, segments) of the fixtures each campaign's method is made for."""
    out = {}
    for name, capture in (("joint", "heading137_lat60_125hz"), ("thesis", "thesis_real_cw_125hz"),
                          ("thesis-bench", "thesis_bench_125hz")):
        session = load_session(str(FIXTURES / f"{capture}.bin"))
        out[name] = session, session_segments(session)
    return out


def test_the_registry_lists_the_methods_and_the_daemon_runs_two():
    assert list(ESTIMATORS) == ["joint", "thesis", "thesis-bench"]
    assert all(estimator(name).name == name for name in ESTIMATORS)
    assert config.METHODS == ("joint", "thesis")
    with pytest.raises(KeyError, match="no method 'kalman' .known: joint, thesis, thesis-bench."):
        estimator("kalman")


def test_options_come_from_named_settings():
    settings = {"fixed_amplitude": True, "drift": False, "alpha_deg": 0.5, "beta_deg": -0.1}
    assert estimator("joint").options(settings) == JointOptions(True, False)
    assert estimator("thesis").options(settings) == ThesisOptions((0.5, -0.1), None)
    with pytest.raises(OptionError, match="alpha_deg: 0.5 given without beta_deg"):  # both or neither
        estimator("thesis").options({"alpha_deg": 0.5})
    assert estimator("thesis-bench").options(settings) is None


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_missing_says_what_a_partial_session_lacks_and_none_on_a_complete_one(sessions, name):
    session, segments = sessions[name]
    method = estimator(name)
    assert method.missing(segments) is None
    first_turn = next(k for k, s in enumerate(segments) if s.kind == "turn")
    partial = method.missing(segments[:first_turn])
    assert partial and ("turn" in partial or " up" in partial), partial
    result = method.solve(session, SITE, segments, method.options({}))
    assert isinstance(result, CalibrationResult) and result.method.startswith(name.split("-")[0])


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_a_solve_refuses_exactly_what_missing_says_in_its_words(sessions, name):
    """One judge per method: on every prefix of its campaign that `missing` finds short, the solve
    refuses with those words (what the daemon's progress shows), never with other reasons."""
    session, segments = sessions[name]
    method = estimator(name)
    short = [k for k in range(len(segments)) if method.missing(segments[:k])]
    assert len(short) >= 3
    for k in short:
        with pytest.raises(CampaignIncomplete) as refused:
            method.solve(session, SITE, segments[:k], method.options({}))
        assert refused.value.reason.endswith(f"it lacks {method.missing(segments[:k])}"), (k, refused.value)


def test_the_bench_names_the_positions_it_lacks(sessions):
    _, segments = sessions["thesis-bench"]
    lacking = estimator("thesis-bench").missing([s for s in segments if s.up != "-Z" and s.kind == "static"])
    assert lacking == "a static with -Z up, a full turn (at least 350 deg)"


def test_a_turn_still_under_way_does_not_complete_the_joint_campaign(sessions):
    _, segments = sessions["joint"]
    level_then_turn = segments[:2]
    assert [s.kind for s in level_then_turn] == ["static", "turn"]
    assert estimator("joint").missing(level_then_turn) == "a static after the turn"
    assert estimator("joint").missing(segments[:3]) is None


def test_the_daemon_asks_the_registry(monkeypatch):
    """The daemon's method comes from the registry by name: a stand-in that always lacks something
    is asked, never solved, and its answer is the daemon's status."""
    class Lacking:
        name = "joint"

        def options(self, settings):
            return None

        def missing(self, segments):
            return "a stand-in's needs"

        def solve(self, *args):
            raise AssertionError("solved although the campaign is incomplete")

    monkeypatch.setitem(ESTIMATORS, "joint", Lacking())
    samples = decode_capture((FIXTURES / "heading137_lat60_125hz.bin").read_bytes()).samples
    details = []
    calibrator = Calibrator(Site(60.0), WarmupConfig(window_s=10.0),
                            listeners=[Callbacks(state=lambda state, detail: details.append(detail))])
    calibrator.feed(samples, 125)
    calibrator.finish()
    assert calibrator.result is None
    assert details[-1].endswith("; waiting for: a stand-in's needs"), details[-1]


def test_every_daemon_methods_settings_are_method_config_fields():
    """The daemon passes its MethodConfig's fields to Estimator.options: a setting without a field is lost."""
    fields = {f.name for f in dataclasses.fields(MethodConfig)}
    for name in DAEMON_METHODS:
        assert estimator(name).settings.keys() <= fields, name


@pytest.mark.parametrize("name", DAEMON_METHODS)
def test_the_configuration_takes_each_methods_settings_from_the_registry(name, tmp_path):
    from calibd.results import result_json
    from test_estimated_terms import ESTIMATED

    base = '[serial]\nport = "/dev/ttyUSB0"\n[site]\nlatitude_deg = 40\n[output]\nstate_dir = "s"\n'
    earlier = tmp_path / "earlier.json"  # a result with estimated factory terms, for the intrinsics setting
    earlier.write_bytes(result_json(ESTIMATED))
    for other in DAEMON_METHODS:
        for key, setting in estimator(other).settings.items():
            value = "90" if key == "index_step_deg" else {bool: "true", float: "0.5", list: f'["{earlier}"]'}[
                setting.kind]
            pair = {"alpha_deg": "\nbeta_deg = 0.5", "beta_deg": "\nalpha_deg = 0.5",
                    "index_sigma_deg": "\nindex_step_deg = 90"}.get(key, "")  # what each needs beside it
            text = base + f'[method]\nname = "{name}"\n{key} = {value}{pair}\n'
            if other == name:
                assert getattr(parse_config(tomllib.loads(text), "c.toml").method, key) in (True, 0.5, 90,
                                                                                          [str(earlier)])
            else:
                with pytest.raises(ConfigError, match=f"c.toml \\[method\\] {key}: .* is not allowed with "
                                                      f'name = "{name}": it is an option of the {other} method'):
                    parse_config(tomllib.loads(text), "c.toml")
