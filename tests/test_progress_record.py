"""The one progress record of a session (calibd.detect.Progress, built by calibd.methods.progress):
its counts, its index headings (modulo 360 deg) and what it says is missing agree by
construction, and once the campaign is complete it says so; the daemon's state, `calibd watch`
and the report all show it."""

from __future__ import annotations

import pytest

from calibd import detect
from calibd.detect import Progress, Segment, heading_deg, index_positions
from calibd.methods import progress


def session(*steps: tuple[str, float], up: str = "+Z") -> list[Segment]:
    """Segments one after the other: ("static", 0) or ("turn", angle in deg), each 10 s (60 s for
    statics), the platform angle following the turns."""
    segments, t, chi = [], 0.0, 0.0
    for k, (kind, value) in enumerate(steps):
        span = 60.0 if kind == "static" else 10.0
        if kind == "static":
            segments.append(Segment("static", k * 100, k * 100 + 50, t, t + span, chi, up=up))
        else:
            segments.append(Segment("turn", k * 100, k * 100 + 50, t, t + span, chi, angle_deg=value,
                                    rate_deg_s=value / span, cruise_start=k * 100 + 5, cruise_stop=k * 100 + 45,
                                    cruise_angle_deg=value * 0.8))
            chi += value
        t += span
    return segments


# level at 0, index statics at 90, 180, 270, then 720 deg more: 990 deg is the 270 deg heading again
NO_ZERO_AFTER_LEVEL = session(("static", 0), ("turn", 90), ("static", 0), ("turn", 90), ("static", 0),
                              ("turn", 90), ("static", 0), ("turn", 720), ("static", 0))


def test_a_heading_is_the_platform_angle_modulo_360_deg():
    assert heading_deg(990.0) == 270.0 and heading_deg(-90.0) == 270.0 and heading_deg(360.0) == 0.0
    assert heading_deg(-0.02) == 0.0  # to 0.1 deg: just short of a whole turn is the 0 deg heading, not 360
    assert [detect.index_heading(a) for a in (0.0, 93.0, 990.0, -356.0, 45.0)] == [0, 1, 3, 0, None]


def test_headings_count_and_missing_agree_where_statics_lie_at_990_deg():
    """The report once said "statics seen at [90, 180, 270, 990] deg ... none at 0 deg" beside
    "4/4 index headings": the level static's heading was counted, and 990 deg not taken modulo 360."""
    record = progress("thesis", NO_ZERO_AFTER_LEVEL)
    assert record == Progress(statics=5, index_headings=3, index_turns=3, full_turns=1, other_turns=0,
                              missing="a static at heading 0 deg after the level static")
    assert record.found() == "5 statics at 3/4 index headings, 3 index turns, 1 full turn, 0 other turns"
    with pytest.raises(ValueError, match=r"none at 0 deg \(mod 360\); statics after it seen at headings "
                                         r"\[90, 180, 270, 270\] deg"):
        index_positions(NO_ZERO_AFTER_LEVEL)
    done = progress("thesis", session(("static", 0), ("turn", 90), ("static", 0), ("turn", 90), ("static", 0),
                                      ("turn", 90), ("static", 0), ("turn", 720), ("static", 0), ("turn", 90),
                                      ("static", 0)))  # 1080 deg: the 0 deg heading
    assert done.index_headings == 4 and done.complete


@pytest.mark.parametrize("steps,statics,missing", [
    ((), 0, "a level static, then a turn and a static after it on the same mounting"),
    ((("static", 0),), 1, "a turn and a static after it on the level static's mounting (+Z up)"),
    ((("static", 0), ("turn", 90)), 1, "a static after the turn"),  # the turn under way is the one waited for
    ((("static", 0), ("turn", 90), ("static", 0)), 2, None),
    ((("static", 0), ("turn", 90), ("static", 0), ("turn", 45)), 2, None),  # a later turn leaves it complete
])
def test_the_joint_record_says_what_is_missing_in_the_terms_of_its_counts(steps, statics, missing):
    record = progress("joint", session(*steps))
    assert (record.statics, record.missing, record.complete) == (statics, missing, missing is None)
    if missing is None:
        assert record.words().endswith("; campaign complete") and record.fields()["missing"] is None
    else:
        assert record.words().endswith(f"; waiting for: {missing}")


def test_the_thesis_record_names_the_headings_and_the_full_turn_it_lacks():
    record = progress("thesis", session(("static", 0), ("turn", -90), ("static", 0)))
    assert record.index_headings == 1
    assert record.missing == ("statics at headings 0, 90, 180 deg and a full turn (at least 350 deg) after the "
                              "level static, then a static")
    turning = progress("thesis", NO_ZERO_AFTER_LEVEL[:-1])  # the full turn under way: it is not waited for
    assert turning.full_turns == 1 and turning.missing == "a static at heading 0 deg after the level static"


def test_the_state_progress_fields_are_the_records():
    """STATE's `progress` (docs/protocol.md): the counts and `missing` under their documented names."""
    record = progress("joint", session(("static", 0), ("turn", 90)))
    assert record.fields() == {"statics": 1, "index_headings": 0, "index_turns": 1, "full_turns": 0,
                               "other_turns": 0, "missing": "a static after the turn"}
