"""Capture and StreamInfo: what the bulk decoder returns, and what a live parser is described by."""

import json
from dataclasses import FrozenInstanceError
from pathlib import Path

import numpy as np
import pytest

from calibd.cli import main as calibd_main
from captures import capture
from stim300.bulk import decode_capture, decode_columns
from stim300.capture import stream_info
from stim300.codec import SAMPLE_DTYPE
from stim300.protocol import INTERNAL_RATE_HZ, Format
from stim300.stream import StreamParser

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def test_a_capture_with_power_up_datagrams_carries_the_sensor_identity():
    data = (FIXTURES / "faults_125hz.bin").read_bytes()
    truth = json.loads((FIXTURES / "faults_125hz.bin.truth.json").read_text())["sensor"]
    info = decode_capture(data).info
    assert info.rate_hz == truth["sample_rate_hz"] == info.format.sample_rate_hz
    assert info.sensor_record().to_dict() == {
        "serial_number": truth["serial_number"], "part_number": f"{truth['part_number']} REV {truth['revision']}",
        "datagram_id": truth["datagram_id"], "sample_rate_hz": truth["sample_rate_hz"], "sample_rate": "125 Hz",
        "acc_range_g": truth["acc_range_g"], "trim": None}
    assert info.configuration is not None and info.configuration.format == info.format


@pytest.mark.parametrize("rate_hz", [125, 250, 1000, 2000])
def test_without_a_configuration_the_rate_comes_from_the_counter_step(rate_hz):
    data, samples, fmt = capture(50, rate=rate_hz)
    info = decode_capture(data, Format(datagram_id=fmt.datagram_id)).info
    assert info.format.sample_rate_hz is None
    assert info.rate_hz == rate_hz and info.stats.counter_step == INTERNAL_RATE_HZ // rate_hz
    assert info.sensor_record().to_dict() == {"serial_number": None, "part_number": None, "datagram_id": "0xA7",
                                    "sample_rate_hz": rate_hz, "sample_rate": f"{rate_hz} Hz", "acc_range_g": None,
                                    "trim": None}


def test_one_datagram_is_too_few_to_know_the_rate():
    data, _, fmt = capture(1, rate=250)
    info = decode_capture(data, Format(datagram_id=fmt.datagram_id)).info
    assert info.stats.datagrams == 1
    assert info.rate_hz is None and info.sensor_record().sample_rate_hz is None


def test_a_live_parser_is_described_as_the_bulk_decoder_describes_the_capture():
    data = (FIXTURES / "faults_125hz.bin").read_bytes()
    parser = StreamParser()
    early = None
    for start in range(0, len(data), 4096):
        parser.feed(data[start:start + 4096])
        early = early or stream_info(parser)
    parser.finish()
    assert stream_info(parser) == decode_capture(data).info
    assert early.stats.datagrams < stream_info(parser).stats.datagrams  # a snapshot: feeding on leaves it
    with pytest.raises(FrozenInstanceError):
        early.rate_hz = 250


def test_columns_hold_the_same_values_and_info_as_rows():
    data = (FIXTURES / "static_turn_2000hz.bin").read_bytes()
    rows = decode_capture(data)
    columns, info = decode_columns(data)
    assert info == rows.info
    assert rows.samples.dtype == SAMPLE_DTYPE
    for name in SAMPLE_DTYPE.names:
        assert np.array_equal(columns[name], rows.samples[name], equal_nan=True), name


def test_calibrate_refuses_a_capture_whose_rate_cannot_be_known(tmp_path, capsys):
    data, _, _ = capture(1, rate=125)
    path = tmp_path / "one.bin"
    path.write_bytes(data)
    assert calibd_main(["calibrate", str(path), "--latitude", "40", "-o", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and "sample rate unknown" in err


def test_a_given_rate_is_known_before_any_datagram():
    parser = StreamParser(Format(sample_rate_hz=500))
    assert stream_info(parser.scanner) == stream_info(parser)
    assert stream_info(parser).rate_hz == 500 and stream_info(parser).stats.datagrams == 0


def test_configuration_warnings_reach_info_results_and_the_daemon_log(tmp_path, capsys):
    """A configuration with an undefined gyro unit is refused: `stim300 info`, calibrate's
    result and the daemon's log all say why."""
    from structlog.testing import capture_logs

    from calibd.daemon import Calibrator
    from calibd.frames import Site
    from calibd.live import replay
    from stim300.cli import main as stim300_main
    from stim300.crc import datagram_crc
    from stim300.protocol import CONFIGURATION
    from stim300.source import CaptureSource
    from stim300.special import Configuration, encode_special

    frame = bytearray(encode_special(Configuration.build(sample_rate_hz=125), False))
    frame[5] = frame[5] & 0xF0 | 5  # gyro unit code 5: not in the byte map
    frame[CONFIGURATION.pre_crc:CONFIGURATION.pre_crc + 4] = datagram_crc(
        bytes(frame[:CONFIGURATION.pre_crc])).to_bytes(4, "big")
    data = bytes(frame) + (FIXTURES / "heading137_lat60_125hz.bin").read_bytes()
    path = tmp_path / "refused.bin"
    path.write_bytes(data)
    assert stim300_main(["info", str(path)]) == 0
    assert "warning          configuration datagram refused: configuration gyro_unit: code 0x5" in \
        capsys.readouterr().out
    out = tmp_path / "r.json"
    assert calibd_main(["calibrate", str(path), "--latitude", "60", "-o", str(out)]) == 0
    warnings = json.loads(out.read_text())["stream"]["warnings"]
    assert len(warnings) == 1 and "gyro_unit" in warnings[0]
    with capture_logs() as logs:
        replay(CaptureSource(data[:200_000]), Calibrator(Site(60.0)))
    said = [e["detail"] for e in logs if e["event"] == "stream_warning"]
    assert len(said) == 1 and "gyro_unit" in said[0]
