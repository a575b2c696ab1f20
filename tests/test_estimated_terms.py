"""Factory terms the data estimated are taken out by every corrected output, after the biases,
and only those: a term its prior set is no measurement. `calibd apply`, the corrected pty's
datagrams, the served corrections (SAMPLES, ROS 2, Foxglove) all go through
`calibd.correction`'s map."""

from dataclasses import replace

import numpy as np
import pytest

from calibd.apply import meta_record
from calibd.correction import ServedCorrection, estimated_maps, sensor_biases
from calibd.serve.correct import Corrector
from captures import capture
from stim300.codec import encode_samples
from stim300.stream import StreamParser
from test_apply import applied_columns, truth_result

SCALE_PPM, MISALIGNMENT_MRAD = 300.0, 0.5


def term(value: float, unit: str, source: str) -> dict:
    return {"value": value, "sigma": 10.0, "prior_sigma": 250.0, "unit": unit, "source": source}


def with_terms(result, **terms):
    """The result with an error budget whose factory terms are those given (name: record)."""
    return replace(result, error_budget={"frame": "housing", "parts": [], "sigma": {},
                                         "factory_residuals": {"terms": terms}})


ESTIMATED = with_terms(truth_result(serial=None), gyro_scale_z=term(SCALE_PPM, "ppm", "estimated"),
                       acc_misalignment_xy=term(MISALIGNMENT_MRAD, "mrad", "estimated"),
                       incl_scale_x=term(400.0, "ppm", "prior"))


def test_the_maps_invert_the_estimated_terms_and_leave_the_prior_ones_out():
    maps = estimated_maps(ESTIMATED)
    assert set(maps) == {"gyro", "acc"}  # the inclinometers' term is the prior's
    np.testing.assert_allclose(maps["gyro"], np.diag([1.0, 1.0, 1 / (1 + SCALE_PPM * 1e-6)]), rtol=1e-15)
    error = np.zeros((3, 3))
    error[0, 1] = MISALIGNMENT_MRAD * 1e-3  # the X axis senses housing Y
    np.testing.assert_allclose(maps["acc"] @ (np.eye(3) + error), np.eye(3), atol=1e-15)
    assert estimated_maps(truth_result()) == {}  # no error budget: nothing estimated


def test_apply_takes_the_bias_off_then_the_estimated_map():
    _, samples, fmt = capture(300, 0xA7, False, rate=250)
    for cluster in ("gyro", "acc", "incl"):
        samples[f"status_{cluster}"] = 0
    data = encode_samples(samples, 0xA7, fmt, False).tobytes()
    plain, _ = applied_columns(truth_result(serial=None), data=data)
    mapped, _ = applied_columns(ESTIMATED, data=data)
    maps = estimated_maps(ESTIMATED)
    np.testing.assert_allclose(mapped["gyro_rad_s"], plain["gyro_rad_s"] @ maps["gyro"].T, rtol=1e-14)
    np.testing.assert_allclose(mapped["acc_m_s2"], plain["acc_m_s2"] @ maps["acc"].T, rtol=1e-14)
    np.testing.assert_array_equal(mapped["incl_m_s2"], plain["incl_m_s2"])
    # a turn at 30 deg/s about Z reads 300 ppm less once corrected: 0.009 deg/s
    assert not np.allclose(mapped["gyro_rad_s"][:, 2], plain["gyro_rad_s"][:, 2], rtol=1e-5, atol=0)
    from calibd.apply import correction
    record = meta_record(correction(ESTIMATED, False, False), "r.json", "0" * 64, ESTIMATED, "c.bin", "x")
    assert set(record["estimated_maps"]) == {"gyro", "acc"}


def test_the_corrected_pty_takes_the_map_out_in_counts():
    _, samples, fmt = capture(200, 0x93, False, rate=2000, seed=3)
    data = encode_samples(samples, 0x93, fmt, False).tobytes()
    out = []
    corrector = Corrector(ESTIMATED)
    StreamParser(fmt, tap=lambda settled: out.append(corrector.apply(settled))).feed(data)
    got = StreamParser(fmt).feed(b"".join(bytes(x) for x in out))  # the CRCs hold: every datagram decodes
    assert len(got) == len(samples)
    bias = sensor_biases(ESTIMATED)
    maps = estimated_maps(ESTIMATED)
    for cluster in ("gyro", "acc"):
        lsb = np.broadcast_to(fmt.scales()[cluster], 3)
        expected = (samples[cluster][:len(got)].astype(np.float64) - bias[cluster]) @ maps[cluster].T
        # within two counts: the bias rounded to a count, then the map's product to the nearest one
        assert np.all(np.abs(got[cluster].astype(np.float64) - expected) <= 2 * lsb), cluster
    wrong = samples["gyro"][:len(got), 2].astype(np.float64) - bias["gyro"][2]  # the bias alone
    assert np.abs(got["gyro"][:, 2] - wrong).max() > 3 * np.broadcast_to(fmt.scales()["gyro"], 3)[2]


def test_a_served_correction_takes_out_the_bias_and_the_map():
    served = ServedCorrection.of(ESTIMATED)
    values = np.array([[1.0, 2.0, 30.0]], np.float32)  # deg/s
    expected = (values - served.bias["gyro"]) @ estimated_maps(ESTIMATED)["gyro"].T
    np.testing.assert_allclose(served.take_out("gyro", values), expected, rtol=1e-6)
    np.testing.assert_allclose(served.take_out("incl", values), values - served.bias["incl"], rtol=1e-7)
    plain = ServedCorrection.of(truth_result(serial=None))
    assert plain.maps == {} and not plain.same_as(served) and served.same_as(ServedCorrection.of(ESTIMATED))
    assert ServedCorrection.of(truth_result(drop=[f"{c}_bias_{a}" for c in ("gyro", "acc", "incl")
                                                  for a in "xyz"])) is None


@pytest.mark.parametrize("name, sensor, row, col, to_unit", [("gyro_scale_z", "gyro", 2, 2, 1e6),
                                                             ("incl_misalignment_zx", "incl", 2, 0, 1e3)])
def test_a_term_name_gives_its_element(name, sensor, row, col, to_unit):
    from calibd.spec import FactoryTerm
    element = FactoryTerm.named(name)
    assert (element.sensor, element.row, element.col, element.to_unit, element.name) == (sensor, row, col,
                                                                                        to_unit, name)
