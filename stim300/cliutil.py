"""Command-line plumbing shared by `stim300` and `calibd`: one-line errors, never a traceback."""

from __future__ import annotations

import argparse
import errno
import os
import stat
import sys

from .errors import Stim300Error, UsageError, os_reason


def package_version() -> str:
    """The installed stim300-calib's version (both command lines' --version, the socket's VERSION).
    importlib.metadata is imported here, when asked: it costs every command's start-up otherwise."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("stim300-calib")
    except PackageNotFoundError:
        return "unknown (not installed)"


class _Version(argparse.Action):
    """--version: "PROG VERSION" on stdout, the version looked up only when asked."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show program's version number and exit"):
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{parser.prog} {package_version()}")
        parser.exit()


class CommandParser(argparse.ArgumentParser):
    """One-line usage errors; a top-level parser (no parent) also answers --version."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if "prog" in kwargs and " " not in kwargs["prog"]:
            self.add_argument("--version", action=_Version)

    def error(self, message):  # one line, not usage + message
        raise UsageError(f"{self.prog}: {message}")


class RunError(Stim300Error):
    """The input was fine but the work failed (an output that cannot be written): one line, exit 1."""


DOCUMENT_LIMIT_BYTES = 16 << 20  # a result, state, noise or truth file is some kB: far more is not one
TEXT_LIMIT_BYTES = 1 << 20  # a configuration or a scenario is some hundred bytes (and is parsed on SIGHUP)


def path_arg(text: str) -> str:
    """argparse type of a file name: an empty one names no file (`-o ""` is not "no output")."""
    if not text:
        raise argparse.ArgumentTypeError("an empty path names no file")
    return text


def _refuse(path, mode: int, what: str) -> None:
    """A one-line UsageError unless `mode` is a regular file's."""
    if stat.S_ISLNK(mode):
        raise UsageError(f"{path}: a symbolic link (not followed), expected a {what}")
    if stat.S_ISDIR(mode):
        raise UsageError(f"{path}: is a directory, expected a {what}")
    if not stat.S_ISREG(mode):
        raise UsageError(f"{path}: not a regular file (a device or FIFO), expected a {what}")


def _cannot_read(path, exc: OSError) -> UsageError:
    if isinstance(exc, FileNotFoundError):
        return UsageError(f"{path}: no such file")
    return UsageError(f"{path}: cannot read: {os_reason(exc)}")


def input_file(path, what: str = "capture file", follow: bool = True) -> None:
    """Refuse, with a one-line UsageError, a path that is not a regular file: a directory, a
    device or FIFO (/dev/zero would be read until memory runs out, a FIFO block), and with
    `follow=False` a symbolic link. Looked at without opening it (opening a device can act)."""
    try:
        mode = (os.stat if follow else os.lstat)(path).st_mode
    except OSError as exc:
        raise _cannot_read(path, exc) from None
    _refuse(path, mode, what)


def open_regular(path, limit_bytes: int | None = None, what: str = "capture file", follow: bool = True):
    """`path` opened for reading (a binary file object), or a one-line UsageError: the one way
    every command opens an input. It must be a regular file, of at most `limit_bytes` when
    given; `follow=False` (a file in a directory the program owns, such as the daemon's state
    directory) refuses a symbolic link. Checked again on the open file, so nothing swapped in
    after the first look is read; opened without blocking, so a FIFO never hangs the open."""
    input_file(path, what, follow)
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | (0 if follow else os.O_NOFOLLOW)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        if exc.errno == errno.ELOOP and not follow:
            _refuse(path, stat.S_IFLNK, what)
        raise _cannot_read(path, exc) from None
    f = os.fdopen(fd, "rb")
    try:
        status = os.fstat(fd)
        _refuse(path, status.st_mode, what)
        if limit_bytes is not None and status.st_size > limit_bytes:
            raise UsageError(f"{path}: {status.st_size} bytes, too large for a {what} ({limit_bytes} at most)")
        os.set_blocking(fd, True)
    except BaseException:
        f.close()
        raise
    return f


def read_input(path, what: str = "capture file", limit_bytes: int | None = None, follow: bool = True) -> bytes:
    """The bytes of an input file (`open_regular`: at most `limit_bytes`, also when the file
    grows while it is read), or a UsageError saying in one line why not."""
    with open_regular(path, limit_bytes, what, follow) as f:
        try:
            data = f.read(-1 if limit_bytes is None else limit_bytes + 1)
        except OSError as exc:
            raise _cannot_read(path, exc) from None
    if limit_bytes is not None and len(data) > limit_bytes:
        raise UsageError(f"{path}: more than {limit_bytes} bytes, too large for a {what}")
    return data


def read_text(path, what: str, limit_bytes: int, follow: bool = True) -> str:
    """The UTF-8 text of a document file (`read_input`'s rules), or a one-line UsageError."""
    try:
        return read_input(path, what, limit_bytes, follow).decode("utf-8")
    except UnicodeDecodeError:
        raise UsageError(f"{path}: cannot read: not UTF-8 text") from None


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
    reason = os_reason(exc)
    usage = exc.errno in (errno.EISDIR, errno.ENOENT, errno.ENOTDIR, errno.EACCES, errno.EPERM, errno.EROFS)
    return (UsageError if usage else RunError)(f"{path}: cannot write: {reason}")


def run_command(parser: argparse.ArgumentParser, argv=None, input_errors: tuple[type[Exception], ...] = ()) -> int:
    """Parse, dispatch to the subcommand's `func`, and turn UsageError and the program's own
    `input_errors` (what is wrong with the input, each one line: calibd's CalibdError) into one
    stderr line and exit 2, RunError into one line and exit 1."""
    prog = parser.prog
    try:
        args = parser.parse_args(argv)
        return args.func(args)
    except (UsageError, RunError, *input_errors) as exc:
        text = str(exc)
        print(text if text.startswith(prog) else f"{prog}: {text}", file=sys.stderr)
        return 1 if isinstance(exc, RunError) else 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `... | head` closed our stdout: nothing more to say, and no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the interpreter flushes at exit
        return 141
    except Exception as exc:  # a fault of the program, not of the input: one line that says so
        print(f"{prog}: internal error: {type(exc).__name__}: {exc} (a fault in {prog}, not in the input: "
              "please report it with the command)", file=sys.stderr)
        return 1
