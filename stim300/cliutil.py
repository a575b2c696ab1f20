"""Command-line plumbing shared by `stim300` and `calibd`: one-line errors, never a traceback."""

from __future__ import annotations

import argparse
import os
import sys

from .errors import UsageError


class CommandParser(argparse.ArgumentParser):
    def error(self, message):  # one line, not usage + message
        raise UsageError(f"{self.prog}: {message}")


def read_input(path: str, what: str = "capture file") -> bytes:
    """The bytes of an input file, or a UsageError saying in one line why not."""
    try:
        with open(path, "rb") as f:
            return f.read()
    except FileNotFoundError:
        raise UsageError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise UsageError(f"{path}: is a directory, expected a {what}") from None
    except OSError as exc:
        raise UsageError(f"{path}: cannot read: {(exc.strerror or str(exc)).lower()}") from None


def run_command(parser: argparse.ArgumentParser, argv=None) -> int:
    """Parse, dispatch to the subcommand's `func`, and turn UsageError into one stderr line."""
    prog = parser.prog
    try:
        args = parser.parse_args(argv)
        return args.func(args)
    except UsageError as exc:
        text = str(exc)
        print(text if text.startswith(prog) else f"{prog}: {text}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `... | head` closed our stdout: nothing more to say, and no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the interpreter flushes at exit
        return 141
    except Exception as exc:  # a fault of the program, not of the input: one line that says so
        print(f"{prog}: internal error: {type(exc).__name__}: {exc} (a fault in {prog}, not in the input: "
              "please report it with the command)", file=sys.stderr)
        return 1
