"""The daemon's state directory: `ResultStore` writes it (result.json, history/, state.json) as a
listener of the calibrator. `calibd status` reads it back without this module (and its logging):
state.json through calibd.documents.load_state, result.json through calibd.results."""

from __future__ import annotations

import errno
import json
import os
import time
from dataclasses import replace
from datetime import datetime, timezone
from enum import Enum
from pathlib import Path

import structlog

from stim300.atomic import write_atomic

from .errors import CalibdError
from .results import CalibrationResult, load_result, result_json

log = structlog.get_logger("calibd")


class StateDirError(CalibdError):
    """A state directory the daemon cannot use (missing parent, not a directory, unwritable, a
    symlink where a file or history/ belongs); one line."""


MAX_PENDING_HISTORY = 100  # history entries held while the state directory cannot be written


class ResultStore:
    """The daemon's state directory, a listener of its Calibrator: result.json (the best result
    of the power-up, replaced atomically and synced, so a crash at any moment leaves it
    readable), history/ (every result, timestamped) and state.json (what `calibd status` shows,
    with `origin`: the port or capture the daemon reads).

    A directory that breaks while the daemon runs (deleted, replaced, unwritable, full) does not
    stop it: the writes wait and are retried at the next event or `retry()`, `degraded` says
    why (also in state.json once it can be written), `on_health(degraded)` hears each change,
    and the log has one `state_dir_error` per outage and `state_dir_recovered` at its end.
    Symlinks inside the directory are never written through."""

    FILES = ("result.json", "state.json")

    def __init__(self, state_dir, origin: dict | None = None, on_health=lambda degraded: None):
        """Prepare the directory and remove the temporary files killed writers left; StateDirError
        when it cannot be used."""
        self.dir = Path(state_dir)
        self.origin = origin or {}
        self.on_health = on_health
        self.degraded: str | None = None  # "cannot write results (why)" while writes fail
        self._kept: CalibrationResult | None = None  # the result in result.json
        self._held_back: str | None = None  # why the newest result is only in history/
        self._pending: dict[Path, tuple[bytes, bool]] = {}  # writes not done yet: path -> (data, durable)
        self._state: dict = {}
        try:
            self._prepare()
            for name in self.FILES:
                self._writable(self.dir / name)
            for folder in (self.dir, self.dir / "history"):
                for orphan in folder.glob(".*.part"):
                    orphan.unlink()
                    log.info("orphan_removed", path=str(orphan))
        except OSError as exc:
            raise StateDirError(f"state directory {self.dir}: {self._why(exc)}") from None

    def previous(self) -> CalibrationResult | None:
        """result.json as an earlier daemon left it (None: none, or unreadable, said in the log).
        Not the kept result: whether it is of the sensor's current power-up is not known until
        the sensor restarts or the stream names another sensor (then the Calibrator marks it
        stale and result.json says so)."""
        path = self.dir / "result.json"
        if path.is_symlink() or not path.is_file():
            return None
        try:
            return load_result(path)
        except (CalibdError, OSError) as exc:
            log.warning("previous_result_unreadable", path=str(path), error=str(exc))
            return None

    def _prepare(self) -> None:
        """The directory and history/ exist (made again if deleted) and are real directories:
        OSError otherwise (history/ a symlink too: it is not followed)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        if not self.dir.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, "not a directory", str(self.dir))
        if not os.access(self.dir, os.W_OK | os.X_OK):
            raise PermissionError(errno.EACCES, "not writable", str(self.dir))
        history = self.dir / "history"
        if history.is_symlink() or history.exists() and not history.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, "not a directory (a symlink is not followed)", str(history))
        history.mkdir(exist_ok=True)

    @staticmethod
    def _writable(path: Path) -> None:
        """OSError when `path` is a symlink (never written through) or a directory."""
        if path.is_symlink():
            raise OSError(errno.ELOOP, "a symlink (not followed)", str(path))
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, "a directory", str(path))

    @staticmethod
    def _why(exc: OSError, where=None) -> str:
        """An OSError in words that stay the same from one attempt to the next: the file meant
        (`where`), not the temporary one."""
        where = where or exc.filename
        return f"{where}: {exc.strerror or exc}" if where else str(exc.strerror or exc)

    def retry(self) -> None:
        """Try the writes that failed again (the daemon's loop calls this while degraded)."""
        if self._pending:
            self._flush()

    def _write(self, path: Path, data: bytes, durable: bool = True) -> None:
        self._pending.pop(path, None)  # newest content last: history keeps its order
        self._pending[path] = (data, durable)
        waiting = [p for p in self._pending if p.parent.name == "history"]
        for dropped in waiting[:-MAX_PENDING_HISTORY]:  # a long outage: memory stays bounded
            del self._pending[dropped]
            log.warning("history_dropped", path=str(dropped), detail="the state directory has been unusable "
                        f"for {MAX_PENDING_HISTORY} results; the oldest waiting one is not kept")
        self._flush()

    def _flush(self) -> None:
        """Every pending write, each tried even when another fails (state.json still says why
        when result.json cannot be written)."""
        problem = None
        try:
            self._prepare()
        except OSError as exc:
            problem = self._why(exc)
        else:
            for path, (data, durable) in list(self._pending.items()):
                try:
                    self._writable(path)
                    write_atomic(path, data, durable, follow=False)  # a link made since: replaced
                    del self._pending[path]
                except OSError as exc:
                    problem = problem or self._why(exc, path)
        self._health(None if problem is None else f"cannot write results ({problem})")

    def _health(self, degraded: str | None) -> None:
        """Log and tell a change between healthy and degraded; state.json then says it."""
        changed = (degraded is None) != (self.degraded is None)
        self.degraded = degraded
        if not changed:
            return
        if degraded is None:
            log.info("state_dir_recovered", state_dir=str(self.dir))
        else:
            log.error("state_dir_error", state_dir=str(self.dir), error=degraded,
                      detail="calibrating on; the writes are retried")
        self.on_health(degraded)
        self._write_state()

    def on_result(self, result: CalibrationResult) -> None:
        """Every result goes to history/; result.json takes it unless it is poorer than a result
        of the same power-up already there (`_poorer`)."""
        text = result_json(result)
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
        history = self.dir / "history" / f"result-{stamp}.json"
        self._write(history, text)
        self._held_back = self._poorer(result)
        if self._held_back is None:
            self._kept = result
            self._write(self.dir / "result.json", text)
        else:
            self._held_back += f"; it is in {history.relative_to(self.dir)} only"
            log.warning("result_held_back", reason=self._held_back)
        self._write_state()

    def _poorer(self, new: CalibrationResult) -> str | None:
        """Why `new` must not replace the result in result.json, or None: it has a poor
        estimate, or it rests on a shorter session and has a larger yaw sigma, while the result
        there is of the same power-up (not stale) and has none."""
        kept = self._kept
        if kept is None or kept.stale is not None or self._poor(kept):
            return None
        if self._poor(new):
            return (f"the new result has poor estimates ({', '.join(self._poor(new))}): "
                    "result.json keeps the better one")
        new_s, kept_s = (0.0 if r.session is None else r.session.duration_s for r in (new, kept))
        new_sigma, kept_sigma = (getattr(r.estimates.get("yaw"), "sigma", None) for r in (new, kept))
        if new_s < kept_s and None not in (new_sigma, kept_sigma) and new_sigma > kept_sigma:
            return (f"the new result's yaw sigma {new_sigma:.2f} deg on {new_s:.0f} s is larger than "
                    f"result.json's {kept_sigma:.2f} deg on {kept_s:.0f} s: result.json keeps the better one")
        return None

    @staticmethod
    def _poor(result: CalibrationResult) -> list[str]:
        """The names of the estimates flagged poor."""
        return [name for name, e in result.estimates.items() if e.quality == "poor"]

    def on_stale(self, result: CalibrationResult) -> None:
        """Rewrite result.json only, as the result it holds marked stale with `result`'s record
        and warning (history keeps it as it was made); a new power-up's result replaces it."""
        marked = result if self._kept is None else replace(
            self._kept, stale=result.stale,
            warnings=(*[w for w in result.warnings if w.startswith("stale:")][:1], *self._kept.warnings))
        self._kept, self._held_back = marked, None
        self._write(self.dir / "result.json", result_json(marked))

    def on_state(self, state: Enum, detail: str, progress: dict | None = None) -> None:
        self._state = {"state": state.value, "detail": detail}
        self._write_state()

    def _write_state(self) -> None:
        if not self._state:
            return
        record = {**self._state, "updated": time.time(), **self.origin,
                  **({"degraded": self.degraded} if self.degraded else {}),
                  **({"held_back": self._held_back} if self._held_back else {})}
        self._write(self.dir / "state.json", (json.dumps(record) + "\n").encode(), durable=False)
