"""The progress bar draws on a terminal only, and ends its line."""

import io

from stim300.progress import Progress


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_silent_off_a_terminal():
    out = io.StringIO()
    with Progress("decode", 100, "B", stream=out) as bar:
        for done in range(0, 101, 10):
            bar.update(done)
    assert out.getvalue() == ""


def test_draws_fraction_and_units_on_a_terminal_and_ends_the_line():
    out = Terminal()
    with Progress("replay", 2000, "B", stream=out, interval_s=0.0) as bar:
        bar.update(500)
        bar.update(2000)
    text = out.getvalue()
    assert "\rreplay [" in text and " 25.0% (500/2000 B" in text and "100.0% (2000/2000 B" in text
    assert text.endswith("\n") and text.count("\n") == 1


def test_redraws_at_most_every_interval_but_always_the_end():
    out = Terminal()
    bar = Progress("report", 10, "steps", stream=out, interval_s=3600)
    for done in range(11):
        bar.update(done)
    bar.close()
    assert out.getvalue().count("\r") == 2  # the first update and the last
