"""Files that appear whole or not at all: written beside the target, renamed into place."""

from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_file(path, durable: bool = True):
    """A binary file object whose content replaces `path` only when the block completes.

    `durable` also syncs the data to disk before the rename, so a power cut leaves the old
    file or the new one; bulk outputs that can be made again skip it (syncing hundreds of MB
    costs seconds). Raises OSError (e.g. missing directory, no permission); the temporary
    file never outlives a failure.
    """
    target = Path(path)
    if target.is_dir():
        raise IsADirectoryError(21, "is a directory", str(target))
    tmp = target.with_name(f".{target.name}.{secrets.token_hex(4)}.part")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies, as for open()
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_atomic(path, data: bytes, durable: bool = True) -> None:
    with atomic_file(path, durable) as f:
        f.write(data)
