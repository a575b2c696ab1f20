"""calibd.correction, the one home of what every corrected output subtracts: the biases in SI
and the sensor's units, the outputs that can take them, and whether a result is the sensor's."""

import numpy as np
import pytest

from calibd.correction import other_sensor, sensor_biases, si_biases, uncorrectable
from calibd.frames import STANDARD_GRAVITY, Site
from calibd.results import make_result
from calibd.units import DEG
from stim300.protocol import AccUnit, GyroUnit
from stim300.special import Configuration
from stim300.records import SensorRecord


def result(**si):
    return make_result("joint", Site(40.0), {name: (value, 1e-6) for name, value in si.items()}, [], [],
                       SensorRecord(serial_number="N1"))


def test_the_biases_are_the_estimates_in_si_and_in_the_sensors_units():
    gyro = {f"gyro_bias_{a}": v for a, v in zip("xyz", (1e-5, -2e-5, 3e-5))}  # rad/s
    acc = {f"acc_bias_{a}": v for a, v in zip("xyz", (1e-3, 2e-3, -5e-3))}  # m/s^2
    partial = {"incl_bias_x": 1e-3, "incl_bias_y": 1e-3}  # no Z: the inclinometers are not corrected
    made = result(**gyro, **acc, **partial)
    si = si_biases(made)
    assert set(si) == {"gyro", "acc"}
    assert np.allclose(si["gyro"], [1e-5, -2e-5, 3e-5]) and np.allclose(si["acc"], [1e-3, 2e-3, -5e-3])
    sensor = sensor_biases(made)  # deg/s, g
    assert np.allclose(sensor["gyro"] * DEG, si["gyro"]) and np.allclose(sensor["acc"] * STANDARD_GRAVITY, si["acc"])


@pytest.mark.parametrize("gyro_unit, acc_unit, incl_unit, words", [
    (GyroUnit.RATE, AccUnit.ACCELERATION, AccUnit.AVERAGE_ACCELERATION, []),
    (GyroUnit.INCREMENTAL_ANGLE_DELAYED, AccUnit.ACCELERATION, AccUnit.ACCELERATION,
     ["gyro incremental_angle_delayed"]),
    (GyroUnit.INTEGRATED_ANGLE, AccUnit.INCREMENTAL_VELOCITY, AccUnit.INTEGRATED_VELOCITY_GS,
     ["gyro integrated_angle", "accelerometer incremental_velocity", "inclinometer integrated_velocity_gs"]),
])
def test_only_rates_and_accelerations_take_a_constant_bias(gyro_unit, acc_unit, incl_unit, words):
    fmt = Configuration.build(gyro_unit=gyro_unit, acc_unit=acc_unit, incl_unit=incl_unit).format
    assert uncorrectable(fmt) == words


@pytest.mark.parametrize("result_serial, serial, other", [
    ("N1", "N1", False), ("N1", "N2", True), (None, "N2", False), ("N1", None, False), (None, None, False)])
def test_a_result_is_of_another_sensor_only_when_both_serial_numbers_say_so(result_serial, serial, other):
    assert other_sensor(result_serial, serial) is other
