"""Streaming parser and bulk decoder: chunking invariance, re-synchronisation, statistics."""

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from captures import capture, power_up, same_samples, stream_decode
from stim300.bulk import decode_capture
from stim300.capture import stream_info
from stim300.crc import datagram_crc
from stim300.codec import SAMPLE_DTYPE, encode_samples
from stim300.reads import READS_DTYPE
from stim300.protocol import CONFIGURATION, NORMAL_LAYOUTS, SERIAL_NUMBER, Format, GyroUnit
from stim300.special import Configuration, PartNumber, SerialNumber, encode_special
from stim300.stream import FOLLOW_BLOCK, Scanner, StreamParser, verified

LONGEST = max(layout.wire_length(True) for layout in NORMAL_LAYOUTS.values())


def assert_same_as_bulk(data: bytes, cuts=(), fmt=None):
    samples, parser = stream_decode(data, cuts, fmt)
    bulk = decode_capture(data, fmt)
    assert same_samples(samples, bulk.samples)
    assert stream_info(parser) == bulk.info
    return samples, parser


def test_clean_stream_decodes_every_sample():
    data, truth, fmt = capture(1000, 0xA7, False, rate=2000)
    samples, parser = assert_same_as_bulk(data, range(0, len(data), 4096))
    assert same_samples(samples, truth)
    s = parser.stats
    assert (s.datagrams, s.crc_errors, s.skipped_bytes, s.lost_samples) == (1000, 0, 0, 0)
    assert parser.format.datagram_id == 0xA7 and parser.format.crlf is False
    assert s.counter_step == 1


def test_crlf_is_detected_without_a_configuration():
    data, truth, _ = capture(100, 0x93, True, rate=125)
    samples, parser = assert_same_as_bulk(data)
    assert same_samples(samples, truth)
    assert parser.format.crlf is True
    assert parser.stats.counter_step == 16


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([(0xA7, False), (0x93, True), (0x90, False), (0xF7, True)]),
       st.lists(st.integers(0, 3000), max_size=40), st.integers(0, 1000))
def test_any_chunking_gives_identical_output(id_crlf, cuts, seed):
    ident, crlf = id_crlf
    data, truth, _ = capture(60, ident, crlf, seed=seed)
    data = data[:3000]
    cuts = [c for c in cuts if c < len(data)]
    reference, ref_parser = stream_decode(data, [])
    samples, parser = stream_decode(data, cuts)
    assert same_samples(samples, reference)
    assert parser.stats.as_dict() == ref_parser.stats.as_dict()


def test_one_byte_at_a_time():
    data, truth, _ = capture(40, 0xA7, True)
    samples, _ = assert_same_as_bulk(data, range(len(data)))
    assert same_samples(samples, truth)


def test_garbage_between_datagrams_is_skipped_and_counted():
    data, truth, fmt = capture(200, 0xA7, False)
    length = NORMAL_LAYOUTS[0xA7].wire_length(False)
    rng = np.random.default_rng(5)
    garbage = bytes(rng.integers(0, 256, 1000, dtype=np.uint8))
    # garbage without id bytes, so nothing in it can pass for a datagram start
    garbage = bytes(b for b in garbage if b not in NORMAL_LAYOUTS and b < 0xB0)
    stream = data[:50 * length] + garbage + data[50 * length:]
    samples, parser = assert_same_as_bulk(stream, [17, 3000, 5000])
    assert same_samples(samples, truth)
    assert parser.stats.skipped_bytes == len(garbage)
    assert parser.stats.lost_samples == 0


def test_bit_flip_costs_one_datagram_and_one_crc_error():
    data, truth, _ = capture(100, 0xA7, False, rate=125)
    length = NORMAL_LAYOUTS[0xA7].wire_length(False)
    corrupted = bytearray(data)
    corrupted[10 * length + 20] ^= 0x04
    samples, parser = assert_same_as_bulk(bytes(corrupted), [333])
    assert same_samples(samples, np.delete(truth, 10))
    s = parser.stats
    assert (s.datagrams, s.crc_errors, s.lost_samples, s.skipped_bytes) == (99, 1, 1, length)


@pytest.mark.parametrize("damage", ["id", "crc", "cr", "lf", "payload"])
@pytest.mark.parametrize("at", [0, 7, FOLLOW_BLOCK - 1, FOLLOW_BLOCK, FOLLOW_BLOCK + 5])
def test_datagrams_checked_at_once_stop_at_the_first_that_fails_as_the_scanner_does(damage, at):
    """`verified` gives the valid prefix of a block whatever breaks the first bad datagram, and a
    stream fed whole (runs checked FOLLOW_BLOCK at a time) decodes as one fed a byte at a time and
    as the bulk decoder, statistics included."""
    data, truth, fmt = capture(2 * FOLLOW_BLOCK + 10, 0x93, True, rate=2000)
    layout = NORMAL_LAYOUTS[0x93]
    length = layout.wire_length(True)
    where = {"id": 0, "crc": layout.pre_crc + 2, "cr": length - 2, "lf": length - 1, "payload": 5}[damage]
    broken = bytearray(data)
    broken[at * length + where] ^= 0x10
    frames = np.frombuffer(bytes(broken), np.uint8).reshape(-1, length)
    assert verified(frames[:at + 3], layout, True) == at
    assert verified(frames[at + 1:at + 4], layout, True) == 3
    whole, parser = assert_same_as_bulk(bytes(broken), fmt=fmt)
    single, _ = assert_same_as_bulk(bytes(broken), range(len(broken)), fmt=fmt)
    assert same_samples(whole, np.delete(truth, at)) and same_samples(single, whole)
    s = parser.stats  # the first datagram has no counter before it to tell a loss
    assert (s.datagrams, s.lost_samples) == (len(truth) - 1, at > 0)
    if damage != "id":  # an id broken makes the datagram's other bytes candidates, whatever they hold
        assert s.crc_errors == 1


def test_missing_crlf_rejects_the_datagram_when_crlf_is_configured():
    data, truth, fmt = capture(10, 0x93, True)
    length = NORMAL_LAYOUTS[0x93].wire_length(True)
    broken = data[:3 * length - 1] + b"\x00" + data[3 * length:]
    samples, parser = assert_same_as_bulk(broken, fmt=fmt)
    assert same_samples(samples, np.delete(truth, 2))
    assert parser.stats.crc_errors == 1


def test_truncated_tail_is_skipped_at_finish():
    data, truth, _ = capture(10, 0xA7, False)
    samples, parser = assert_same_as_bulk(data[:-7])
    assert same_samples(samples, truth[:9])
    assert parser.stats.skipped_bytes == NORMAL_LAYOUTS[0xA7].wire_length(False) - 7


@pytest.mark.parametrize("rate,step", [(125, 16), (2000, 1), (500, 4)])
def test_counter_gaps_are_lost_samples_across_the_wrap(rate, step):
    data, truth, fmt = capture(600, 0x91, False, rate=rate)  # counters wrap several times at every rate
    length = NORMAL_LAYOUTS[0x91].wire_length(False)
    drop = [5, 6, 7, 100, 255, 256, 257, 400]
    kept = b"".join(data[i * length:(i + 1) * length] for i in range(600) if i not in drop)
    for given_fmt in (None, fmt):  # inferred step and configured rate agree
        samples, parser = assert_same_as_bulk(kept, [1000], given_fmt)
        assert len(samples) == 600 - len(drop)
        assert parser.stats.lost_samples == len(drop)
        assert parser.stats.counter_step == step


@pytest.mark.parametrize("missing,counted", [(15, 15), (16, 0), (17, 1)])
def test_counter_gaps_of_a_whole_cycle_alias(missing, counted):
    data, _, _ = capture(40, 0x90, False, rate=125)  # 16 datagrams per counter cycle at 125 Hz
    length = NORMAL_LAYOUTS[0x90].wire_length(False)
    kept = data[:5 * length] + data[(5 + missing) * length:]
    _, parser = assert_same_as_bulk(kept, fmt=Format(sample_rate_hz=125))
    assert parser.stats.lost_samples == counted  # the counter cannot tell a whole cycle


def test_datagram_id_change_counts_as_configuration_change():
    a, ta, _ = capture(30, 0xA7, False, seed=1)
    b, tb, _ = capture(30, 0x93, False, seed=2)
    samples, parser = assert_same_as_bulk(a + b, [100, 2000])
    assert same_samples(samples, np.concatenate([ta, tb]))
    assert parser.stats.config_changes == 1
    assert parser.format.datagram_id == 0x93


@settings(max_examples=80, deadline=None)
@given(st.binary(max_size=3000), st.lists(st.integers(0, 3000), max_size=10))
def test_random_bytes_never_raise_and_match_bulk(blob, cuts):
    assert_same_as_bulk(blob, [c for c in cuts if c < len(blob)])


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10**6), st.lists(st.tuples(st.integers(0, 5000), st.sampled_from(["flip", "drop", "insert"])),
                                        max_size=8))
def test_corrupted_streams_match_bulk(seed, damage):
    data, _, _ = capture(80, 0xA7, True, seed=seed)
    buf = bytearray(data)
    rng = np.random.default_rng(seed)
    for pos, kind in damage:
        pos %= len(buf)
        if kind == "flip":
            buf[pos] ^= 1 << int(rng.integers(8))
        elif kind == "drop":
            del buf[pos:pos + int(rng.integers(1, 70))]
        else:
            buf[pos:pos] = bytes(rng.integers(0, 256, int(rng.integers(1, 70)), dtype=np.uint8))
    samples, parser = assert_same_as_bulk(bytes(buf), [int(x) for x in rng.integers(0, len(buf) + 1, 5)])
    assert parser.stats.datagrams == len(samples)


def test_memory_stays_bounded_on_endless_garbage():
    parser = StreamParser()
    rng = np.random.default_rng(0)
    for _ in range(50):
        parser.feed(bytes(rng.integers(0, 256, 20000, dtype=np.uint8)))
        assert len(parser._buf) < LONGEST + 2
    assert parser.stats.datagrams == 0
    assert parser.stats.skipped_bytes > 990000


def test_t_host_stamps_the_samples_a_read_completes():
    data, _, _ = capture(3, 0x90, False)
    parser = StreamParser()
    first = parser.feed(data[:30], t_host=1.5)  # completes the first datagram (18 B) only
    second = parser.feed(data[30:], t_host=2.5)
    assert first["t_host"].tolist() == [1.5]
    assert second["t_host"].tolist() == [2.5, 2.5]


def test_reads_parsed_together_stamp_each_datagram_by_the_read_that_completed_it():
    """As each read fed on its own would: the first datagram of a stream whose CR LF is not known
    is accepted only once the 2 bytes after it say there is none, here in the third read."""
    data, _, _ = capture(3, 0x90, False)  # 18 B each
    cuts = [18, 19, 40]
    alone, _ = stream_decode(data, cuts)
    together, _ = stream_decode(data, cuts, together=[0])
    assert alone["t_host"].tolist() == together["t_host"].tolist() == [2.0, 2.0, 3.0]
    known, _ = stream_decode(data, cuts, Format(crlf=False), together=[0])
    assert known["t_host"].tolist() == [0.0, 2.0, 3.0]  # told: accepted with its last byte
    reads = np.array([(18, 0.0), (19, 1.0), (40, 2.0), (54, 3.0)], READS_DTYPE)
    assert decode_capture(data, reads=reads).samples["t_host"].tolist() == [2.0, 2.0, 3.0]  # offline alike


def test_configuration_datagram_is_adopted():
    config = Configuration.build(sample_rate_hz=500, acc_range_g=30, crlf=True, temp_included=False)
    assert config.datagram_id == 0x93
    data, truth, _ = capture(100, 0x93, True, rate=500, acc_range_g=30)
    # the user's guess (10 g, no CR LF) is overridden by what the sensor says
    samples, parser = assert_same_as_bulk(power_up(config) + data, [7, 50], Format(acc_range_g=10, crlf=False))
    assert same_samples(samples, truth)
    assert parser.format == config.format
    assert parser.scanner.configuration == config
    assert str(parser.scanner.part_number) == "84167-4400003-321 REV K"
    assert parser.scanner.serial_number.text == "N25582405002002"
    assert parser.stats.counter_step == 4
    assert (parser.stats.restarts, parser.stats.config_changes, parser.stats.special_datagrams) == (0, 0, 3)


def test_sensor_restart_is_counted_and_does_not_count_as_loss():
    config = Configuration.build(sample_rate_hz=125)
    first, t1, _ = capture(50, 0xA7, False, rate=125, seed=1)
    second, t2, _ = capture(50, 0xA7, False, rate=125, seed=2)  # counter starts again at 0
    first = power_up(config) + first[:40 * 59]
    samples, parser = assert_same_as_bulk(first + power_up(config) + second, [1000, 3001])
    assert same_samples(samples, np.concatenate([t1[:40], t2]))
    assert (parser.stats.restarts, parser.stats.lost_samples, parser.stats.config_changes) == (1, 0, 0)
    assert parser.stats.restart_datagrams == [40]  # the second power-up's first sample


def test_requested_part_number_is_not_a_restart():
    data, truth, _ = capture(30, 0xA7, False, rate=125)
    stream = data[:10 * 59] + encode_special(PartNumber("84167-4400003-321", "K"), False) + data[11 * 59:]
    samples, parser = assert_same_as_bulk(stream)
    assert parser.stats.restarts == 0
    assert parser.stats.lost_samples == 1  # the special datagram replaced one normal datagram


def test_requested_part_and_serial_numbers_mid_stream_are_no_restart():
    """`N` then `I` answered while data flow: the counter chain goes on, nothing is cut."""
    data, truth, _ = capture(40, 0xA7, False, rate=125)
    truth["status_gyro"] = truth["status_acc"] = truth["status_incl"] = 0
    data = encode_samples(truth, 0xA7, Format(sample_rate_hz=125), False).tobytes()
    stream = (data[:10 * 59] + encode_special(PartNumber("84167-4400003-321", "K"), False)
              + encode_special(SerialNumber("N25582405002002"), False) + data[12 * 59:])
    samples, parser = assert_same_as_bulk(stream, [10 * 59 + 20])
    assert (parser.stats.restarts, parser.stats.restart_datagrams) == (0, [])
    assert parser.stats.lost_samples == 2  # the two answers replaced two normal datagrams
    assert parser.scanner.serial_number.text == "N25582405002002"


@pytest.mark.parametrize("with_configuration", [True, False])
def test_a_power_up_sequence_mid_stream_is_a_restart(with_configuration):
    """Part number, serial number, then the configuration datagram, or (that one lost) data
    with the start-up status bit: the sensor restarted."""
    config = Configuration.build(sample_rate_hz=125)
    first, _, _ = capture(30, 0xA7, False, rate=125, seed=1)
    second, t2, _ = capture(30, 0xA7, False, rate=125, seed=2)  # counter from 0 again
    t2["status_gyro"][0] = 0x40  # the start-up bit
    second = encode_samples(t2, 0xA7, Format(sample_rate_hz=125), False).tobytes()
    sequence = power_up(config) if with_configuration else power_up(config)[:-len(encode_special(config, False))]
    _, parser = assert_same_as_bulk(first + sequence + second)
    assert (parser.stats.restarts, parser.stats.restart_datagrams) == (1, [30])
    assert parser.stats.lost_samples == 0


def test_new_configuration_counts_as_change():
    a = Configuration.build(sample_rate_hz=125)
    b = Configuration.build(sample_rate_hz=2000)
    data, _, _ = capture(20, 0xA7, False, rate=125)
    _, parser = assert_same_as_bulk(encode_special(a, False) + data + encode_special(b, False) + data)
    assert parser.stats.config_changes == 1
    assert parser.format.sample_rate_hz == 2000


def with_crc(frame: bytearray) -> bytes:
    covered = bytes(frame[:CONFIGURATION.pre_crc])
    frame[CONFIGURATION.pre_crc:CONFIGURATION.pre_crc + 4] = datagram_crc(covered).to_bytes(4, "big")
    return bytes(frame)


def test_an_undefined_code_no_value_depends_on_is_kept_and_said():
    frame = bytearray(encode_special(Configuration.build(sample_rate_hz=125), False))
    frame[6] |= 0x07  # gyro LPF Y code 7: not in the byte map
    data, truth, _ = capture(5, 0xA7, False, rate=125)
    samples, parser = assert_same_as_bulk(with_crc(frame) + data)
    assert same_samples(samples, truth)
    assert parser.stats.undecodable_specials == 0 and parser.scanner.configuration is not None
    warnings = stream_info(parser).warnings
    assert len(warnings) == 1 and "gyro_lpf_hz" in warnings[0] and "0x7" in warnings[0]


def test_a_configuration_with_an_undefined_unit_is_refused_loudly():
    frame = bytearray(encode_special(Configuration.build(sample_rate_hz=125), False))
    frame[5] = frame[5] & 0xF0 | 5  # gyro unit code 5: undefined, and every gyro value depends on it
    data, truth, _ = capture(5, 0xA7, False, rate=125)
    samples, parser = assert_same_as_bulk(with_crc(frame) + data)
    assert same_samples(samples, truth)  # decoded as before (the given or default format)
    assert parser.stats.undecodable_specials == 1 and parser.scanner.configuration is None
    warnings = stream_info(parser).warnings
    assert len(warnings) == 1 and warnings[0].startswith("configuration datagram refused")
    assert "gyro_unit" in warnings[0] and "0x5" in warnings[0]


def test_a_5g_incremental_angle_unit_decodes_in_its_units():
    """A real unit's configuration (undefined bit-rate code): gyro in deg, acc in 5 g counts."""
    config = bytes.fromhex("bc4b1f06407144407044407044400c00003330000000a91f9809")
    fmt = Format(datagram_id=0x93, crlf=False, sample_rate_hz=125, gyro_unit=GyroUnit.INCREMENTAL_ANGLE,
                 acc_range_g=5)
    truth = np.zeros(20, SAMPLE_DTYPE)
    truth["datagram_id"], truth["gyro"], truth["acc"], truth["incl"] = 0x93, 1.0, 1.0, 0.5
    truth["temp_gyro"] = truth["temp_acc"] = truth["temp_incl"] = truth["aux"] = np.nan
    truth["counter"] = np.arange(20) * 16 % 256
    samples, parser = assert_same_as_bulk(config + encode_samples(truth, 0x93, fmt, False).tobytes())
    assert np.all(samples["gyro"] == 1.0) and np.all(samples["acc"] == 1.0)
    info = stream_info(parser)
    assert info.format == fmt and info.format.units()["gyro"] == "deg"
    assert len(info.warnings) == 1 and "bit_rate_code" in info.warnings[0]


def test_each_accelerometer_axis_is_scaled_by_its_own_range():
    fmt = Format(datagram_id=0x93, crlf=False, sample_rate_hz=125, acc_range_g=(5, 10, 80))
    data, truth, _ = capture(30, 0x93, False, rate=125, acc_range_g=(5, 10, 80))
    config = encode_special(dataclasses.replace(Configuration.build(sample_rate_hz=125, temp_included=False),
                                                acc_range_g=(5, 10, 80)), False)
    samples, parser = assert_same_as_bulk(config + data)
    assert parser.format == fmt
    assert same_samples(samples, truth)
    big = np.zeros(1, SAMPLE_DTYPE)
    big["datagram_id"], big["acc"] = 0x93, [[3.0, 7.0, 60.0]]  # beyond 5 g on Y, beyond 10 g on Z
    big["temp_gyro"] = big["temp_acc"] = big["temp_incl"] = big["aux"] = np.nan
    decoded, _ = stream_decode(config + encode_samples(big, 0x93, fmt, False).tobytes(), [])
    assert decoded["acc"][0].tolist() == [3.0, 7.0, 60.0]


def test_a_run_counted_at_once_ends_the_power_up_sequence_as_single_datagrams_do():
    """A part number, normal data taken by the bulk decoder's vectorised path, then a serial
    number: the serial number was requested, not a restart (as when the scanner takes the data)."""
    scanner = Scanner(None, lambda offset, ident: None)
    scanner.count_counters(np.arange(10, dtype=np.uint8))
    for special in (PartNumber("84167-4400003-321", "K"), SerialNumber("N25582405002002")):
        frame = encode_special(special, False)
        if special.kind is SERIAL_NUMBER:
            scanner.count_counters(np.arange(10, 20, dtype=np.uint8))
        assert scanner.step(frame, 0, final=True) == len(frame)
    assert (scanner.stats.restarts, scanner.stats.special_datagrams) == (0, 2)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 2500), max_size=30), st.integers(0, 1000))
def test_tap_sees_every_byte_once_in_order_with_each_datagrams_offset(cuts, seed):
    data, truth, _ = capture(50, 0x93, True, rate=125, seed=seed)
    data = b"\x00junk" + data[:1200] + b"\xff" + data[1200:]
    settled = []
    parser = StreamParser(tap=settled.append)
    edges = [0, *sorted({c for c in cuts if c < len(data)}), len(data)]
    samples = np.concatenate([*(parser.feed(data[a:b]) for a, b in zip(edges, edges[1:])), parser.finish()])
    assert b"".join(s.data for s in settled) == data
    assert same_samples(np.concatenate([s.samples for s in settled]), samples)
    for s in settled:
        for layout, fmt, offsets, start, stop in s.runs:
            assert np.all(np.frombuffer(s.data, np.uint8)[offsets] == layout.datagram_id)
            redecoded = decode_capture(b"".join(s.data[o:o + layout.wire_length(fmt.crlf)] for o in offsets), fmt)
            assert same_samples(redecoded.samples, s.samples[start:stop])


@settings(max_examples=20, deadline=None)
@given(st.lists(st.integers(0, 3000), max_size=20))
def test_tap_gives_each_special_datagram_as_sent_with_the_feed_that_settles_it(cuts):
    specials = [encode_special(PartNumber("84167-4400003-321", "K"), True),
                encode_special(SerialNumber("N25582405002002"), True),
                encode_special(Configuration.build(sample_rate_hz=125, crlf=True), True)]
    data, _, _ = capture(40, 0x93, True, rate=125, seed=1)
    data = b"".join(specials) + data[:1000] + b"\x00junk" + specials[1] + data[1000:]
    settled = []
    parser = StreamParser(tap=settled.append)
    edges = [0, *sorted({c for c in cuts if c < len(data)}), len(data)]
    for a, b in zip(edges, edges[1:]):
        parser.feed(data[a:b])
    parser.finish()
    assert [frame for s in settled for frame in s.specials] == [*specials, specials[1]]
    assert all(frame in s.data for s in settled for frame in s.specials)
