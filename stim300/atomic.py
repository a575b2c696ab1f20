"""Files that appear whole or not at all: written beside the target, renamed into place.

A target that exists and is not a regular file (a device such as /dev/null, a FIFO, a
terminal) is written in place instead: renaming onto it would replace the device node itself,
so `-o /dev/null` run as root would destroy /dev/null. A directory is refused.

Symbolic links: an output named on the command line may be a link the user made on purpose
(`-o latest.json` pointing at today's file, `-o /dev/stdout`), so by default a link is followed:
the link stays and what it points at is written. A file inside a directory the program owns (a
state directory) is written with `follow=False`: a link there is replaced like any file, never
followed, so it can never aim the write at a device or at a file elsewhere.
"""

from __future__ import annotations

import os
import secrets
import stat
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_file(path, durable: bool = True, follow: bool = True):
    """A binary file object whose content replaces `path` only when the block completes.

    `durable` also syncs the data to disk before the rename, so a power cut leaves the old
    file or the new one; bulk outputs that can be made again skip it (syncing hundreds of MB
    costs seconds). `follow` (see the module): whether a symbolic link at `path` is followed.
    Raises OSError (e.g. missing directory, no permission, a full device); the temporary file
    never outlives a failure.
    """
    try:  # followed: /dev/stdout -> /proc/self/fd/1 -> a pipe
        mode = (os.stat if follow else os.lstat)(path).st_mode
    except FileNotFoundError:
        mode = None
    if mode is not None and stat.S_ISDIR(mode):
        raise IsADirectoryError(21, "is a directory", str(path))
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        with _in_place(path) as f:  # opened by its own name: a pipe behind /dev/stdout has no path
            yield f
        return
    target = Path(os.path.realpath(path)) if follow else Path(path)
    tmp = target.with_name(f".{target.name}.{secrets.token_hex(4)}.part")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # a new file (never a link); the umask applies
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, target)
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)


@contextmanager
def _in_place(target):
    """A device or FIFO opened for writing, never created or renamed over. Opened without
    blocking, so a FIFO nobody reads fails at once (ENXIO) instead of hanging; the writes then
    block as usual. Every write error (ENOSPC from /dev/full) is raised by the close at the latest."""
    fd = os.open(target, os.O_WRONLY | os.O_NONBLOCK | os.O_NOCTTY)
    os.set_blocking(fd, True)
    with os.fdopen(fd, "wb") as f:
        yield f


def in_place(path) -> bool:
    """Whether `atomic_file(path)` writes in place: `path` (followed) is a device or FIFO, so
    nothing can be written beside it."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def write_atomic(path, data: bytes, durable: bool = True, follow: bool = True) -> None:
    with atomic_file(path, durable, follow) as f:
        f.write(data)
