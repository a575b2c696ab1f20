"""The progress bar draws on a terminal only, ends its line, and lets lines printed meanwhile stand alone."""

import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from captures import Terminal, command_env
from stim300.progress import Progress

ROOT = Path(__file__).resolve().parents[1]


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


def screen(output: str) -> list[str]:
    """The lines a terminal shows for `output`: a carriage return goes to the line's start,
    ESC [K erases to its end, other characters overwrite."""
    lines, line, col = [], [], 0
    for part in re.split(r"(\r|\n|\x1b\[K)", output):
        if part == "\r":
            col = 0
        elif part == "\n":
            lines.append("".join(line))
            line, col = [], 0
        elif part == "\x1b[K":
            del line[col:]
        else:
            line[col:col + len(part)] = part
            col += len(part)
    return lines + (["".join(line)] if line else [])


def test_a_line_printed_above_the_bar_clears_it_first_and_the_bar_comes_back_under_it():
    terminal = Terminal()
    bar = Progress("replay", 100, "B", stream=terminal, interval_s=0.0)
    out = bar.above(terminal)
    bar.update(40)
    print("[SOLVED] solved on 662 s", file=out, flush=True)
    bar.update(100)
    bar.close()
    print("summary", file=out)
    shown = screen(terminal.getvalue())
    assert shown[0] == "[SOLVED] solved on 662 s"
    assert shown[1].startswith("replay [") and "100.0%" in shown[1]
    assert shown[2:] == ["summary"]


def test_lines_above_an_idle_bar_are_plain():
    terminal, plain = Terminal(), io.StringIO()
    bar = Progress("replay", 100, stream=terminal, interval_s=0.0)
    print("before", file=bar.above(plain))
    assert plain.getvalue() == "before\n" and terminal.getvalue() == ""
    off = Progress("replay", 100, stream=io.StringIO(), interval_s=0.0)
    off.update(50)
    print("line", file=off.above(plain))
    assert plain.getvalue() == "before\nline\n"


@pytest.mark.slow
def test_replay_on_one_terminal_never_glues_a_state_line_to_the_bar():
    """calibd replay draws its bar on stderr and prints states on stdout: on one terminal each
    state line stands alone, and the bar is seen between them."""
    master, slave = os.openpty()
    capture = ROOT / "fixtures/thesis_real_ccw_125hz.bin"
    child = subprocess.Popen([sys.executable, "-m", "calibd", "replay", str(capture),
                              "--latitude", "40.59129"], stdout=slave, stderr=slave, stdin=subprocess.DEVNULL,
                             cwd=ROOT, env=command_env())
    os.close(slave)
    chunks = []
    while True:
        try:
            chunk = os.read(master, 65536)
        except OSError:  # EIO: the child closed the terminal
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(master)
    assert child.wait(timeout=60) == 0
    output = b"".join(chunks).decode()
    shown = screen(output)
    states = [line for line in shown if line.startswith("[")]
    assert len(states) >= 3 and any("[SOLVED]" in line for line in states)
    assert not [line for line in shown if "%" in line and "[SOLVED]" in line or re.search(r"\)\[[A-Z]", line)]
    assert all(line.startswith("[") for line in shown if "solved on" in line)
    assert "\r\x1b[K[" in output  # a state line came while the bar was drawn, and cleared it
