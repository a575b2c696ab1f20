"""The shipped captures are exactly what fixtures/make_fixtures.py makes, and agree with their truth."""

import hashlib
import importlib.util
import json
from pathlib import Path

import pytest

from stim300.bulk import decode_capture

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
spec = importlib.util.spec_from_file_location("make_fixtures", FIXTURES / "make_fixtures.py")
make_fixtures = importlib.util.module_from_spec(spec)
spec.loader.exec_module(make_fixtures)
SCENARIOS = make_fixtures.fixtures()


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_fixture_is_reproducible_and_matches_its_truth(name):
    data, truth = make_fixtures.build(SCENARIOS[name])
    shipped = (FIXTURES / f"{name}.bin").read_bytes()
    assert hashlib.sha256(shipped).hexdigest() == hashlib.sha256(data).hexdigest(), "stale: run make_fixtures.py"
    assert (FIXTURES / f"{name}.bin.truth.json").read_bytes() == truth
    record = json.loads(truth)
    decoded = decode_capture(shipped)
    samples, info = decoded.samples, decoded.info
    faults = record["faults"]
    lost = set(faults["dropped_samples"]) | set(faults["bit_flipped_samples"])
    assert len(samples) == record["samples"] - len(lost)
    assert info.stats.restarts == (faults["restart_at_sample"] is not None)
    restart = faults["restart_at_sample"]
    assert info.stats.restart_datagrams == (() if restart is None else (restart - sum(k < restart for k in lost),))
    assert f"0x{info.datagram_id:02X}" == record["sensor"]["datagram_id"]
    assert info.rate_hz == record["sensor"]["sample_rate_hz"]


def test_fixtures_stay_small():
    total = sum(p.stat().st_size for p in FIXTURES.iterdir() if p.is_file())
    assert total < 35e6
