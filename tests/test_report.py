"""`calibd report`: the HTML embeds every figure and tables exactly the result's numbers, beside the
thesis method's and the truth; the figures' decomposition is the joint fit's; one-line errors."""

import base64
import contextlib
import io
import json
import os
import re
import shutil
import sys
import xml.etree.ElementTree as ET
from dataclasses import replace
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from calibd.calibrate import calibrate_capture
from calibd.methods.joint import joint_fit, joint_real_case
from calibd.methods.thesis import thesis_real_case
from calibd.cli import load_session, open_capture
from calibd.cli import main as calibd_main
from calibd.estimators.joint import JointOptions
from calibd.frames import Site
from calibd import detect
from calibd.figures import (YAW_MARKER, earth_rate_figure, earth_rate_fit, earth_rate_seen, earth_term, guide_points,
                            north_chi_deg, platform_axis, timeline_figure)
from calibd.noise import characterise
from calibd.report import (FAR_SIGMAS, MATPLOTLIB_MISSING, _estimates_table, _segments_table, analysis_start_s,
                           read_truth, thesis_comparison, write_report)
from calibd.segments import session_segments
from calibd.results import write_result
from calibd.session import power_up_session
from calibd.units import value_sigma_texts

FIXTURES = Path(__file__).resolve().parent.parent / "fixtures"
CAPTURE = str(FIXTURES / "thesis_real_cw_125hz.bin")
SITE = Site(40.59129, 0.0, 9.79956)  # the thesis's (docs/method.md, The site)
FIGURES = ("timeline", "earth_rate", "allan")


class FakeTerminal(io.StringIO):
    def isatty(self):
        return True


class Cells(HTMLParser):
    """Every <td data-name> cell of the rows of one table, and every src/href/alt attribute."""

    def __init__(self, table_id: str):
        super().__init__()
        self.table_id, self.inside, self.rows, self.cell = table_id, False, {}, None
        self.row = None
        self.attributes = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.attributes += [(tag, k, v) for k, v in attrs if k in ("src", "href", "alt", "title")]
        if tag == "table":
            self.inside = a.get("id") == self.table_id
        elif self.inside and tag == "tr" and "data-estimate" in a:
            self.row = self.rows.setdefault(a["data-estimate"], {})
        elif self.inside and tag == "td" and "data-name" in a and self.row is not None:
            self.cell = [a["data-name"], a.get("data-value"), ""]

    def handle_data(self, data):
        if self.cell is not None:
            self.cell[2] += data

    def handle_endtag(self, tag):
        if tag == "td" and self.cell is not None:
            name, value, text = self.cell
            self.row[name] = (None if value is None else float(value), text)
            self.cell = None
        elif tag == "table":
            self.inside = False


def parse(page: str, table_id: str = "estimates") -> Cells:
    cells = Cells(table_id)
    cells.feed(page)
    return cells


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """The joint result of the thesis fixture, by the library (faster than the command), naming
    its capture as `calibd calibrate` does."""
    directory = tmp_path_factory.mktemp("report")
    capture = open_capture(CAPTURE)
    session = power_up_session(capture)
    result = calibrate_capture(capture, lambda s: joint_real_case(s, SITE), start_s=0.0)
    assert result.capture["sha256"] == capture.identity["sha256"]
    write_result(directory / "result.json", result)
    return {"dir": directory, "result": result, "session": session, "path": directory / "result.json"}


@pytest.fixture(scope="module")
def rendered(made):
    terminal = FakeTerminal()
    written = write_report(made["path"], open_capture(CAPTURE), made["dir"] / "report.html", stream=terminal)
    return made | {"written": written, "bar": terminal.getvalue(), "page": (made["dir"] / "report.html").read_text()}


@pytest.fixture(scope="module")
def with_svg(rendered):
    """The same report by the command with --svg, beside the first."""
    output = rendered["dir"] / "vector.html"
    with contextlib.redirect_stdout(io.StringIO()):
        assert calibd_main(["report", str(rendered["path"]), CAPTURE, "-o", str(output), "--svg"]) == 0
    return {"dir": rendered["dir"] / "vector_files", "page": output.read_text()}


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_files_exist_and_are_pngs(rendered):
    d = rendered["dir"]
    assert rendered["written"] == [d / "report.html"] + [d / "report_files" / f"{f}.png" for f in FIGURES]
    for name in FIGURES:
        data = (d / "report_files" / f"{name}.png").read_bytes()
        assert data.startswith(b"\x89PNG\r\n\x1a\n")
        image = Image.open(io.BytesIO(data))
        image.verify()
        assert image.size[0] >= 800 and image.size[1] >= 400
    assert not list(d.glob(".*part")) and not list((d / "report_files").glob(".*part"))  # no temporaries left


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_no_svg_unless_asked_and_the_page_names_only_files_written(rendered):
    """The SVGs cost as much again as the PNGs: written only with --svg, and a page without them
    links no file that is not there."""
    assert sorted(p.name for p in (rendered["dir"] / "report_files").iterdir()) == sorted(f"{f}.png" for f in FIGURES)
    named = {value for _, key, value in parse(rendered["page"]).attributes if key != "src"}
    assert named == {f"report_files/{f}.png" for f in FIGURES}
    assert all((rendered["dir"] / name).is_file() for name in named)
    assert ".svg" not in rendered["page"]


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_svg_beside_each_png_with_its_text(rendered, with_svg):
    """--svg: vector copies for print, SVG documents whose labels are text, not paths, dated
    nowhere; the PNGs are the same bytes as without it, and the page differs only in its links."""
    for name, words in (("timeline", "platform rate [deg/h]"), ("earth_rate", "yaw ="), ("allan", "Allan deviation")):
        data = (with_svg["dir"] / f"{name}.svg").read_bytes()
        root = ET.fromstring(data)
        assert root.tag == "{http://www.w3.org/2000/svg}svg"
        text = " ".join("".join(e.itertext()) for e in root.iter("{http://www.w3.org/2000/svg}text"))
        assert words in text, name
        assert b"<dc:date>" not in data
        named = {(tag, key) for tag, key, value in parse(with_svg["page"]).attributes
                 if value == f"vector_files/{name}.svg"}
        assert ("a", "href") in named
        assert (with_svg["dir"] / f"{name}.png").read_bytes() == \
            (rendered["dir"] / "report_files" / f"{name}.png").read_bytes()
    links = re.compile(r" Files?: .*?</figcaption>")
    assert links.sub("", with_svg["page"].replace("vector_files/", "report_files/")) == links.sub("", rendered["page"])


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_html_embeds_and_names_every_figure_and_loads_nothing(rendered):
    page, d = rendered["page"], rendered["dir"]
    for name in FIGURES:
        data = base64.b64encode((d / "report_files" / f"{name}.png").read_bytes()).decode()
        assert f'src="data:image/png;base64,{data}"' in page  # the very bytes of the PNG file
        named = {(tag, key) for tag, key, value in parse(page).attributes if value == f"report_files/{name}.png"}
        assert {("img", "alt"), ("a", "href")} <= named
    sources = [v for tag, k, v in parse(page).attributes if k == "src"]
    assert len(sources) == len(FIGURES) and all(v.startswith("data:image/png;base64,") for v in sources)
    assert "<link" not in page and "<script" not in page and "url(" not in page and "@import" not in page


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_table_numbers_equal_the_result_file(rendered):
    saved = json.loads((rendered["dir"] / "result.json").read_text())
    rows = parse(rendered["page"]).rows
    assert list(rows) == list(saved["estimates"])
    for name, e in saved["estimates"].items():
        texts = value_sigma_texts(e["value"], e["sigma"])  # shown as calibd calibrate prints them
        for column, text in zip(("value", "sigma"), texts):
            exact, shown = rows[name][column]
            assert exact == e[column] and shown == text
            assert float(shown) == pytest.approx(e[column], rel=0.05, abs=0.05 * e["sigma"])  # rounded at the sigma


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_thesis_and_truth_columns(rendered):
    rows = parse(rendered["page"]).rows
    thesis = thesis_real_case(rendered["session"], SITE).estimates
    record = json.loads(Path(CAPTURE + ".truth.json").read_text())
    truth, carried = record["truth"], record["bias_during_capture"]
    expected = {"pitch": (truth["pitch_deg"],) * 2, "yaw": (truth["yaw_deg"],) * 2, "beta": (truth["beta_deg"],) * 2,
                "gyro_bias_y": (truth["gyro_bias_deg_h"][1], carried["gyro_bias_deg_h"]["session"][1]),
                "acc_bias_z": (truth["acc_bias_mg"][2], carried["acc_bias_mg"]["session"][2]),
                "incl_bias_x": (truth["incl_bias_mg"][0], carried["incl_bias_mg"]["session"][0])}
    for name, (scenario, in_data) in expected.items():
        assert rows[name]["truth"][0] == scenario
        assert rows[name]["carried"][0] == in_data
        assert rows[name]["error"][0] == pytest.approx(rendered["result"].estimates[name].value - in_data)
        assert abs(rows[name]["error"][0]) < 3 * rows[name]["sigma"][0]  # the joint 1-sigma is honest here
    assert "<th>error / sigma</th>" in rendered["page"]
    for name, row in rows.items():
        exact, shown = row["error_sigmas"]
        assert exact == pytest.approx(row["error"][0] / row["sigma"][0])
        assert float(shown) == round(exact, 1) and not shown.startswith("-0.0"), name  # no "-0.0"
        assert abs(exact) < 3, name  # no estimate here is off by 3 sigma
    for name, e in thesis.items():
        assert rows[name]["thesis"][0] == pytest.approx(e.value, rel=1e-12, abs=1e-12)
    assert "thesis-linear" in rendered["page"]


def test_error_beyond_three_sigma_is_highlighted(made):
    """A sigma too small for the error it has: the cell says so."""
    result = made["result"]
    truth = read_truth(CAPTURE)
    error = result.estimates["roll"].value - truth[1]["roll"]
    narrow = replace(result, estimates=result.estimates | {
        "roll": replace(result.estimates["roll"], sigma=abs(error) / (2 * FAR_SIGMAS))})
    table = _estimates_table(narrow, "not solved", truth)
    assert re.findall(r'<td class="num far" data-name="error_sigmas"[^>]*>([-0-9.]+)</td>', table) == \
        [f"{6.0 if error > 0 else -6.0:.1f}"]


def test_timeline_shows_the_small_signals(made):
    """Panels of their own for the horizontal gyros (deg/h, the platform rate removed) and the
    horizontal accelerometers and inclinometers (mg), on one time axis; over the full turn the
    gyro X panel keeps the bias (the Earth rate averages out), not the tens of deg/s of the turn."""
    session, result = made["session"], made["result"]
    segments = session_segments(session)
    roles = detect.segment_roles(segments)
    fig = timeline_figure(session, segments, roles, (0.0, ""), platform_axis(result)).drawing
    labels = [ax.get_ylabel() for ax in fig.axes]
    assert labels == ["gyro [deg/s]", "horizontal gyros less\nplatform rate [deg/h]", "accelerometer [m/s$^2$]",
                      "horizontal\naccelerometers [mg]", "horizontal\ninclinometers [mg]", "gyro temperature\n[degC]"]
    assert all(ax.get_shared_x_axes().joined(fig.axes[0], ax) for ax in fig.axes)
    gyro_x = fig.axes[1].get_lines()[0]
    turn = next(s for s, r in zip(segments, roles) if r == "full turn")
    t, x = gyro_x.get_data()
    inside = (t > turn.start_s + 2) & (t < turn.end_s - 2)  # the constant-rate part
    assert inside.sum() > 8  # bins of 0.8 s
    assert np.mean(x[inside]) == pytest.approx(result.estimates["gyro_bias_x"].value, abs=10.0)
    low, high = fig.axes[1].get_ylim()
    assert high - low < 500  # deg/h: the turn's 1e5 deg/h do not set the scale
    accel_x = fig.axes[3].get_lines()[0].get_data()[1]
    static = session.acc[:1000, 0].mean() * 1000 / 9.80665  # mg
    assert np.median(accel_x[:50]) == pytest.approx(static, abs=0.5)


def test_timeline_of_a_unit_without_inclinometers():
    session = load_session(str(FIXTURES / "gyro_acc_125hz.bin"))
    segments = session_segments(session)
    fig = timeline_figure(session, segments, detect.segment_roles(segments), (0.0, ""), None).drawing
    assert [t.get_text() for t in fig.axes[4].texts] == ["no inclinometers in this datagram"]


@pytest.mark.slow  # a whole session fitted and drawn
def test_earth_rate_figure_marks_the_yaw():
    """The phase line sits where the IMU's X axis points North, chi = -yaw (yaw counter-clockwise
    about Up, as chi): there the fitted X term peaks. A heading far from 0 tells the sign."""
    site = Site(60.0, 120.0)
    session = load_session(str(FIXTURES / "heading137_lat60_125hz.bin"))
    result = joint_real_case(session, site)
    yaw = result.estimates["yaw"].value
    assert 120 < yaw < 150
    fig = earth_rate_figure(session, site, session_segments(session), result).drawing
    marker = [line for line in fig.axes[0].get_lines() if line.get_gid() == YAW_MARKER]
    assert len(marker) == 1
    assert marker[0].get_xdata() == pytest.approx([north_chi_deg(yaw)] * 2, abs=1e-9)
    assert north_chi_deg(yaw) == pytest.approx(360 - yaw)
    chi, x_term = fig.axes[0].get_lines()[0].get_data()  # gyro X: fitted Earth-rate term
    assert chi[np.argmax(x_term)] == pytest.approx(north_chi_deg(yaw), abs=1.5)
    assert any(f"yaw = {yaw:.2f}" in t.get_text() for t in fig.axes[0].texts)


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_segments_are_the_campaigns(rendered):
    roles = re.findall(r"<tr><td>\d+</td><td>([a-z ]+)</td>", rendered["page"].split('id="segments"')[1])
    assert roles == ["static", "index turn"] * 4 + ["static", "full turn", "static"]


def _statics_at(*chis: float) -> list[detect.Segment]:
    """Statics at these platform angles (deg) with the turns between them."""
    out = []
    for k, chi in enumerate(chis):
        if k:
            angle = chi - chis[k - 1]
            out.append(detect.Segment("turn", 100 * k - 50, 100 * k, k - 0.5, k, chis[k - 1], angle_deg=angle,
                                      rate_deg_s=angle * 2, cruise_start=100 * k - 40, cruise_stop=100 * k - 10,
                                      cruise_angle_deg=angle * 0.8))
        out.append(detect.Segment("static", 100 * k, 100 * k + 50, k, k + 0.5, chi, up="+Z"))
    return out


def test_the_thesis_column_says_what_the_campaign_lacks_with_headings_modulo_360():
    """A daemon's session whose statics after the level one lie at 90, 180, 270 and 990 deg: the
    thesis method lacks the 0 deg heading, and the count of headings says 3/4, not 4/4."""
    segments = _statics_at(0.0, 90.0, 180.0, 270.0, 990.0)
    note = thesis_comparison(None, SITE, segments)  # the session is not needed to say what is lacking
    assert note == ("its campaign lacks a static at heading 0 deg after the level static; found 5 statics at 3/4 "
                    "index headings, 3 index turns, 1 full turn, 0 other turns")
    table = _segments_table(segments, detect.segment_roles(segments))
    assert "<th>heading [deg]</th>" in table
    assert "<td class='num'>990.000</td><td class='num'>270.0</td>" in table  # chi, and its heading


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_progress_bar_on_a_terminal_only(rendered):
    bar = rendered["bar"]
    assert bar.startswith("\rreport [") and "100.0%" in bar and bar.endswith("\n")


@pytest.mark.slow  # a whole session fitted and drawn
@pytest.mark.parametrize("drift", [False, True])
def test_earth_rate_decomposition_is_the_joint_fit(made, drift):
    """What the Earth-rate figure plots, seen minus fitted term, must be the fit's own residuals:
    a sign or axis slip in the report's reading of the model shows here."""
    session = made["session"]
    fitted = earth_rate_fit(session, SITE, JointOptions(drift=drift), session_segments(session))
    g = fitted.gyro
    residual = earth_rate_seen(fitted) - earth_term(g.params, g.chi)
    assert np.allclose(residual.std(axis=0), g.residual_rms, rtol=1e-9)
    assert np.abs(residual.mean(axis=0)).max() < 1e-3 * g.residual_rms.min()
    amplitude = np.hypot(*earth_term(g.params, np.array([0.0, np.pi / 2]))[:, 0])
    assert amplitude == pytest.approx(g.amplitude_check[0], rel=1e-3)  # X sees the whole horizontal rate


@pytest.mark.slow  # the whole joint fit, twice
def test_earth_rate_figure_redoes_only_the_gyro_fit_of_a_result_of_the_same_fit(made):
    """A joint result of this session: the gyro fit alone is redone and yaw is the result's; they
    equal the whole fit's. A result whose recorded Earth rate differs (other data, options or
    software) gets the whole fit, whose yaw the caption compares with the result's."""
    session, result = made["session"], made["result"]
    segments = session_segments(session)
    whole = joint_fit(session, SITE, JointOptions(), segments)
    cheap = earth_rate_fit(session, SITE, JointOptions(), segments, result)
    assert cheap.yaw == (result.estimates["yaw"].value_si, result.estimates["yaw"].sigma_si)
    assert cheap.yaw == pytest.approx((whole.fit.estimates["yaw"], whole.fit.sigmas["yaw"]), rel=1e-12)
    assert (cheap.segments, cheap.first, cheap.inp.statics) == (whole.segments, whole.first, whole.inp.statics)
    for name in ("params", "chi", "chi_rate"):
        assert np.array_equal(getattr(cheap.gyro, name), getattr(whole.fit.gyro, name))
    assert (cheap.gyro.noise_scale, cheap.gyro.amplitude_check) == (whole.fit.gyro.noise_scale,
                                                                    whole.fit.gyro.amplitude_check)
    recorded, yaw = result.checks["earth_rate_horizontal_deg_h"], result.estimates["yaw"]
    other = replace(result, checks=result.checks | {"earth_rate_horizontal_deg_h": recorded | {
        "fitted": recorded["fitted"] * 1.001}}, estimates=result.estimates | {"yaw": replace(yaw, value=yaw.value + 1)})
    assert earth_rate_fit(session, SITE, JointOptions(), segments, other).yaw == (whole.fit.estimates["yaw"],
                                                                                  whole.fit.sigmas["yaw"])


def test_allan_guides_pass_through_the_values_read(made):
    """The readings come in their own units (deg/sqrt(h), m/s/sqrt(h)): the guides must land back
    on the curve they were read from (white noise rules at 1 s, so the -1/2 line meets the curve;
    the inclinometers' flicker, 0.06 mg and more along gravity, lifts the curve there by a few %)."""
    for noise in characterise(made["session"]).values():
        (tau_rw, at_rw), (tau_bi, at_bi), rising = guide_points(noise)
        curve_at_1s = np.exp(np.interp(0.0, np.log(noise.taus_s), np.log(noise.adev)))
        assert tau_rw == 1.0 and at_rw == pytest.approx(curve_at_1s, rel=0.04), noise.name
        assert at_bi == noise.adev.min() and tau_bi == noise.taus_s[np.argmin(noise.adev)]
        if rising is not None:
            assert noise.adev_low.min() < rising[1] < noise.adev_high.max()


@pytest.mark.slow  # a whole session fitted and drawn
def test_analysis_starts_where_the_result_did():
    """A `calibd calibrate --start` result records its offset; without it (older results) its first
    segment says where its data began, and the segments found from there are the result's (an
    off-by-one-sample start would move them)."""
    capture = str(FIXTURES / "warmup_then_protocol_125hz.bin")
    result = joint_real_case(load_session(capture, 450.0), SITE)
    assert analysis_start_s(result) == 450.0
    start = analysis_start_s(replace(result, stream=replace(result.stream, start_s=None)))
    assert start == pytest.approx(450.0, abs=1e-5)
    again = joint_real_case(load_session(capture, start), SITE)
    assert again.segments == result.segments and again.estimates == result.estimates


def run(argv, capsys):
    code = calibd_main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_command_without_truth_file(rendered, tmp_path, capsys):
    capture = tmp_path / "copy.bin"
    shutil.copy(CAPTURE, capture)
    code, out, err = run(["report", rendered["dir"] / "result.json", capture, "-o", tmp_path / "r.html"], capsys)
    assert code == 0, err
    assert err == ""  # no bar when stderr is not a terminal
    assert f"report: {tmp_path / 'r.html'}" in out and "timeline.png" in out
    assert (tmp_path / "r_files" / "earth_rate.png").exists()
    page = (tmp_path / "r.html").read_text()
    rows = parse(page).rows
    assert all(r["truth"] == r["carried"] == r["error"] == (None, "n/a") for r in rows.values())
    assert "error / sigma" not in page and not any("error_sigmas" in r for r in rows.values())
    assert rows["yaw"]["value"][0] == rendered["result"].estimates["yaw"].value


def test_matplotlib_missing_is_one_line(made, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    code, _, err = run(["report", made["path"], CAPTURE, "-o", tmp_path / "r.html"], capsys)
    assert code == 2
    assert err == MATPLOTLIB_MISSING + "\n"
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("case, message", [
    ("missing result", "no such file"),
    ("not json", "not JSON"),
    ("other schema", "is 'something/1', not a calibd.result file"),
    ("no estimates", "the result has no estimates"),
    ("missing capture", "no such file"),
    ("other capture", "not the result's capture"),
    ("other turning sense, same datagram count", "bytes, but"),
    ("truncated by one byte", "8450517 bytes, but"),
    ("one byte changed", "same size with SHA-256"),
    ("no capture record, other capture", "datagrams, but the result was made from a capture of"),
    ("capture record not an object", "capture is"),
    ("no output directory", "cannot write: no such directory"),
    ("output is a directory", "is a directory"),
])
def test_bad_input_is_one_line(made, tmp_path, capsys, case, message):
    result, capture, output = made["path"], CAPTURE, tmp_path / "r.html"
    if case == "missing result":
        result = tmp_path / "absent.json"
    elif case == "not json":
        result = tmp_path / "bad.json"
        result.write_text("{not json")
    elif case == "other schema":
        result = tmp_path / "other.json"
        result.write_text('{"schema": "something/1"}')
    elif case == "no estimates":
        result = tmp_path / "empty.json"
        result.write_text(json.dumps({"schema": "calibd.result/1", "method": "joint", "site": made["result"].site}))
    elif case == "missing capture":
        capture = tmp_path / "absent.bin"
    elif case == "other capture":
        capture = FIXTURES / "warmup_then_protocol_125hz.bin"
    elif case == "other turning sense, same datagram count":
        capture = FIXTURES / "thesis_real_ccw_125hz.bin"
    elif case in ("truncated by one byte", "one byte changed"):
        data = bytearray(Path(CAPTURE).read_bytes())
        if case == "one byte changed":
            data[len(data) // 2] ^= 0x01
        capture = tmp_path / "edited.bin"
        capture.write_bytes(data[:-1] if case == "truncated by one byte" else data)
    elif case in ("no capture record, other capture", "capture record not an object"):
        doc = json.loads(Path(result).read_text())
        doc["capture"] = "elsewhere"
        if case == "no capture record, other capture":
            del doc["capture"]
            capture = FIXTURES / "warmup_then_protocol_125hz.bin"
        result = tmp_path / "edited.json"
        result.write_text(json.dumps(doc))
    elif case == "no output directory":
        output = tmp_path / "absent" / "r.html"
    else:
        output = tmp_path
    code, out, err = run(["report", result, capture, "-o", output], capsys)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and message in err, err
    assert "Traceback" not in err


def test_a_truth_file_that_is_no_regular_file_is_no_truth(tmp_path):
    """CAPTURE.truth.json is read only as a regular file: a FIFO of that name would hang the
    report, a link to /dev/zero read until memory runs out."""
    capture = tmp_path / "c.bin"
    capture.write_bytes(b"")
    truth = tmp_path / "c.bin.truth.json"
    os.mkfifo(truth)
    assert read_truth(str(capture)) is None
    truth.unlink()
    truth.symlink_to("/dev/zero")
    assert read_truth(str(capture)) is None


@pytest.mark.slow  # the whole report drawn (the `rendered` fixture)
def test_a_failed_report_leaves_the_previous_one(rendered, tmp_path, monkeypatch):
    """The page and its figures are replaced together or not at all: on a full disk the earlier
    report stays as it was, and nothing of the failed run is left."""
    output = tmp_path / "report.html"
    shutil.copy(rendered["dir"] / "report.html", output)
    shutil.copytree(rendered["dir"] / "report_files", tmp_path / "report_files")
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    real = os.fdopen

    def full(fd, mode="r", *args, **kwargs):  # every file written is on a full disk
        if "w" in mode:
            device = os.open("/dev/full", os.O_WRONLY)
            os.dup2(device, fd)
            os.close(device)
        return real(fd, mode, *args, **kwargs)

    monkeypatch.setattr(os, "fdopen", full)
    with pytest.raises(OSError, match="No space left on device"):
        write_report(rendered["path"], open_capture(CAPTURE), output)
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.html", "report_files"]

