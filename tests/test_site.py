"""The site's ranges have one home, the Site: every way in refuses a value out of range with its words."""

import pytest

from calibd.cli import main as calibd_main
from calibd.errors import CalibdError, SiteError
from calibd.frames import G0_RANGE_M_S2, HEIGHT_RANGE_M, LATITUDE_RANGE_DEG, Site

# (option, TOML key, value, the Site's words)
OUT_OF_RANGE = [
    ("--latitude", "latitude_deg", "95", "95.0 is not a latitude in [-90, 90] deg"),
    ("--latitude", "latitude_deg", "-90.5", "-90.5 is not a latitude in [-90, 90] deg"),
    ("--height", "height_m", "9500", "9500.0 is not a height in [-500, 9000] m"),
    ("--g0", "g0", "9.5", "9.5 is not an Earth gravity in [9.7, 9.9] m/s^2"),
]


def site_table(key: str, value: str) -> str:
    values = {"latitude_deg": "40.5", key: value}
    return "[site]\n" + "".join(f"{k} = {v}\n" for k, v in values.items())


def one_line_refusal(argv, capsys) -> str:
    code = calibd_main(argv)
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    return err.strip()


@pytest.mark.parametrize("option,key,value,words", OUT_OF_RANGE)
def test_the_site_refuses_out_of_range_values_with_a_calibd_error(option, key, value, words):
    values = {"latitude_deg": 40.5, key: float(value)}
    with pytest.raises(SiteError) as caught:
        Site(**values)
    assert isinstance(caught.value, CalibdError) and caught.value.field == key
    assert str(caught.value) == f"site {key}: {words}"


@pytest.mark.parametrize("option,key,value,words", OUT_OF_RANGE)
def test_every_way_in_gives_the_same_refusal(option, key, value, words, tmp_path, capsys):
    args = ["--latitude", "40.5"] if option != "--latitude" else []
    by_option = one_line_refusal(["calibrate", "x.bin", *args, option, value, "-o", "r.json"], capsys)
    assert by_option.endswith(f"argument {option}: {words}")

    config = tmp_path / "calibd.toml"
    config.write_text(f'[serial]\nport = "/dev/ttyUSB0"\n{site_table(key, value)}[output]\nstate_dir = "s"\n')
    by_config = one_line_refusal(["run", "--config", str(config)], capsys)
    assert by_config.endswith(f"calibd.toml [site] {key}: {words}")

    scenario = tmp_path / "scenario.toml"
    scenario.write_text(f'{site_table(key, value)}[[segments]]\ntype = "static"\nduration_s = 10\n')
    by_scenario = one_line_refusal(["simulate", str(scenario), "-o", str(tmp_path / "c.bin")], capsys)
    assert by_scenario.endswith(f"scenario.toml [site] {key}: {words}")


@pytest.mark.parametrize("field,bounds", [("latitude_deg", LATITUDE_RANGE_DEG), ("height_m", HEIGHT_RANGE_M),
                                          ("g0", G0_RANGE_M_S2)])
def test_the_range_ends_are_accepted(field, bounds):
    for value in bounds:
        site = Site(**({"latitude_deg": 0.0} | {field: value}))
        assert getattr(site, field) == value
