"""Command-line plumbing shared by `stim300` and `calibd`: one-line errors, never a traceback."""

from __future__ import annotations

import argparse
import errno
import os
import stat
import sys
from importlib.metadata import PackageNotFoundError, version

from .errors import Stim300Error, UsageError


def package_version() -> str:
    """The installed stim300-calib's version (both command lines' --version, the socket's VERSION)."""
    try:
        return version("stim300-calib")
    except PackageNotFoundError:
        return "unknown (not installed)"


class CommandParser(argparse.ArgumentParser):
    """One-line usage errors; a top-level parser (no parent) also answers --version."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if "prog" in kwargs and " " not in kwargs["prog"]:
            self.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")

    def error(self, message):  # one line, not usage + message
        raise UsageError(f"{self.prog}: {message}")


class RunError(Stim300Error):
    """The input was fine but the work failed (an output that cannot be written): one line, exit 1."""


def input_file(path: str, what: str = "capture file") -> None:
    """Refuse, with a one-line UsageError, a path that is not a regular file: a directory, or a
    device or FIFO (/dev/zero would be read until memory runs out)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise UsageError(f"{path}: no such file") from None
    except OSError as exc:
        raise UsageError(f"{path}: cannot read: {(exc.strerror or str(exc)).lower()}") from None
    if stat.S_ISDIR(mode):
        raise UsageError(f"{path}: is a directory, expected a {what}")
    if not stat.S_ISREG(mode):
        raise UsageError(f"{path}: not a regular file (a device or FIFO), expected a {what}")


def read_input(path: str, what: str = "capture file") -> bytes:
    """The bytes of an input file, or a UsageError saying in one line why not."""
    input_file(path, what)
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as exc:
        raise UsageError(f"{path}: cannot read: {(exc.strerror or str(exc)).lower()}") from None


def not_an_input(output, *inputs) -> None:
    """Refuse an output that is one of the command's inputs (or a link to it): `-o CAPTURE` would
    replace the capture with what was made from it."""
    for given in inputs:
        try:
            same = given is not None and os.path.samefile(output, given)
        except OSError:
            same = False  # the output does not exist yet
        if same:
            raise UsageError(f"{output}: is the input {given}: writing it would destroy the input")


def write_error(path, exc: OSError) -> Exception:
    """The one-line error for an output that cannot be written: a directory or a missing parent
    is the user's (UsageError, exit 2); a full disk or a FIFO nobody reads is the run's (exit 1)."""
    if exc.errno == errno.ENXIO:
        return RunError(f"{path}: cannot write: a FIFO that no process reads")
    reason = (exc.strerror or str(exc)).lower()
    usage = exc.errno in (errno.EISDIR, errno.ENOENT, errno.ENOTDIR, errno.EACCES, errno.EPERM, errno.EROFS)
    return (UsageError if usage else RunError)(f"{path}: cannot write: {reason}")


def run_command(parser: argparse.ArgumentParser, argv=None) -> int:
    """Parse, dispatch to the subcommand's `func`, and turn UsageError (exit 2) and RunError
    (exit 1) into one stderr line."""
    prog = parser.prog
    try:
        args = parser.parse_args(argv)
        return args.func(args)
    except (UsageError, RunError) as exc:
        text = str(exc)
        print(text if text.startswith(prog) else f"{prog}: {text}", file=sys.stderr)
        return 2 if isinstance(exc, UsageError) else 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `... | head` closed our stdout: nothing more to say, and no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the interpreter flushes at exit
        return 141
    except Exception as exc:  # a fault of the program, not of the input: one line that says so
        print(f"{prog}: internal error: {type(exc).__name__}: {exc} (a fault in {prog}, not in the input: "
              "please report it with the command)", file=sys.stderr)
        return 1
