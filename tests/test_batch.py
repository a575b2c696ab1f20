"""`calibd batch`: every power-up of many captures on Dask into one fleet table, the same as
single `calibd calibrate` runs, on a local cluster and on a scheduler and workers started here,
through a killed worker and an interrupted batch; bad inputs as rows, a bad cluster as one line."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from calibd import fleettable
from calibd.batch import BatchSettings, capture_paths, merged, plan
from calibd.cli import main as calibd_main
from calibd.frames import Site
from captures import ROOT, calibd, command_env, wait_until
from fleet_captures import G0, LATITUDE

SITE = ["--latitude", LATITUDE, "--g0", G0]
FIXTURES = ROOT / "fixtures"
SETTINGS = BatchSettings("joint", Site(float(LATITUDE), 0.0, float(G0)))


def single_results(paths: list[Path], directory: Path) -> dict[str, str]:
    """Each capture's `calibd calibrate` result file, made in one child process with one BLAS
    thread, as every batch worker has: the threads' count changes a fit's last bits."""
    script = ("import sys\nfrom calibd.cli import main\n"
              "for k, path in enumerate(sys.argv[1:]):\n"
              f"    assert main(['calibrate', path, '-o', f'{directory}/{{k}}.json', *{SITE!r}]) == 0\n")
    subprocess.run([sys.executable, "-c", script, *map(str, paths)], check=True, stdout=subprocess.DEVNULL,
                   env=command_env(OPENBLAS_NUM_THREADS="1"), cwd=ROOT)
    return {str(path): (directory / f"{k}.json").read_text() for k, path in enumerate(paths)}


def batch(*args, env=None, **options) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "calibd.cli", "batch", *map(str, args), *SITE], cwd=ROOT,
                          env=command_env(**(env or {})), capture_output=True, text=True, **options)


@pytest.mark.slow
def test_a_batch_is_24_single_calibrations_exactly(fleet_batch, tmp_path):
    directory, captures, table, out, err = fleet_batch
    assert "24 captures done (24 power-ups calibrated, 0 refused; 0 captures failed, 0 duplicates)" in out
    assert "batch: 24/24 captures done" in err
    rows = fleettable.read_rows(table)
    assert [r["capture"] for r in rows] == sorted(str(c.path) for c in captures)
    singles = single_results([c.path for c in captures], tmp_path)
    for row in rows:
        assert row["status"] == "ok" and row["error"] is None
        assert row["result"] == singles[row["capture"]], row["capture"]  # byte for byte
        doc = json.loads(row["result"])
        assert row["serial_number"] == doc["sensor"]["serial_number"]
        assert row["session_id"] == doc["session_id"] and row["power_up"] == 1 and row["power_ups"] == 1
        for name, estimate in doc["estimates"].items():
            assert (row[name], row[f"{name}_sigma"]) == (estimate["value"], estimate["sigma"])
    when = {c.path.name: c.path.stat().st_mtime for c in captures}
    assert all(abs(r["capture_time"].timestamp() - when[Path(r["capture"]).name]) < 1e-5 for r in rows)
    copy = tmp_path / "again.parquet"
    copy.write_bytes(table.read_bytes())
    again = batch(directory, "-o", copy, "--workers", "2")  # everything is in the table already
    assert again.returncode == 0 and "0 captures done" in again.stdout and "24 already in the table" in again.stdout
    assert fleettable.read_rows(copy) == rows


def start(*command: str, directory: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dask", *command], cwd=directory, env=command_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGKILL)
    process.wait(10)


@pytest.mark.slow
def test_a_cluster_started_apart_survives_a_killed_worker(fleet_batch, tmp_path):
    """A scheduler and two workers as a lab runs them; one worker killed once rows come in: the
    batch completes on the other, every row once, the same rows as a local cluster gives."""
    directory, captures, *_ = fleet_batch
    some = [str(c.path) for c in captures if c.day < 4]  # 12 captures
    scheduler_file = tmp_path / "scheduler.json"
    scheduler = start("scheduler", "--port", "0", "--no-dashboard", "--scheduler-file", str(scheduler_file),
                      directory=tmp_path)
    workers = []
    try:
        wait_until(scheduler_file.exists, "the scheduler file", timeout=30)
        workers = [start("worker", "--scheduler-file", str(scheduler_file), "--nthreads", "1", "--no-dashboard",
                         "--name", f"w{k}", directory=tmp_path) for k in range(2)]
        table = tmp_path / "remote.parquet"
        journal = tmp_path / "remote.parquet.journal"
        running = calibd("batch", *some, "-o", table, "--scheduler", scheduler_file, *SITE)
        wait_until(lambda: len(list(journal.glob("part-*.parquet"))) >= 2, "two captures done", timeout=120)
        stop(workers[0])
        out, err = running.communicate(timeout=300)
        assert running.returncode == 0, err.decode()
        remote = fleettable.read_rows(table)
        assert sorted(r["capture"] for r in remote) == sorted(some) and all(r["status"] == "ok" for r in remote)
        local = tmp_path / "local.parquet"
        assert batch(*some, "-o", local, "--workers", "1").returncode == 0
        assert remote == fleettable.read_rows(local)
    finally:
        for process in (*workers, scheduler):
            stop(process)


@pytest.mark.slow
def test_an_interrupted_batch_computes_only_what_is_missing(fleet_batch, tmp_path):
    directory, captures, *_ = fleet_batch
    some = [str(c.path) for c in captures if c.day < 3]  # 9 captures
    table = tmp_path / "fleet.parquet"
    running = calibd("batch", *some, "-o", table, "--workers", "1", *SITE)
    journal = tmp_path / "fleet.parquet.journal"
    wait_until(lambda: len(list(journal.glob("part-*.parquet"))) >= 3, "three captures done", timeout=120)
    running.send_signal(signal.SIGTERM)
    out, err = running.communicate(timeout=60)
    assert running.returncode == 130 and "stopped" in err.decode()
    kept = fleettable.read_rows(table)
    assert 3 <= len(kept) < len(some) and not journal.exists()
    rest = batch(*some, "-o", table, "--workers", "1")
    assert rest.returncode == 0, rest.stderr
    assert f"{len(some) - len(kept)} captures done" in rest.stdout
    assert f"{len(kept)} already in the table" in rest.stdout
    rows = fleettable.read_rows(table)
    assert sorted(r["capture"] for r in rows) == sorted(some)
    assert [r for r in rows if r["capture"] in {k["capture"] for k in kept}] == kept  # not computed again


@pytest.mark.slow
def test_a_killed_batch_keeps_its_journal_for_the_next_run(fleet_batch, tmp_path):
    directory, captures, *_ = fleet_batch
    some = [str(c.path) for c in captures if c.day < 2]
    table = tmp_path / "fleet.parquet"
    running = calibd("batch", *some, "-o", table, "--workers", "1", *SITE, start_new_session=True)
    journal = tmp_path / "fleet.parquet.journal"
    wait_until(lambda: len(list(journal.glob("part-*.parquet"))) >= 2, "two captures done", timeout=120)
    os.killpg(running.pid, signal.SIGKILL)  # no chance to fold the journal in
    running.wait(10)
    assert not table.exists() and len(list(journal.glob("part-*.parquet"))) >= 2
    rest = batch(*some, "-o", table, "--workers", "1")
    assert rest.returncode == 0, rest.stderr
    assert "already in the table" in rest.stdout and not rest.stdout.endswith(" 0 already in the table\n")
    assert sorted(r["capture"] for r in fleettable.read_rows(table)) == sorted(some) and not journal.exists()


@pytest.mark.slow
def test_bad_inputs_are_rows_with_their_reason(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    good = folder / "a.bin"
    good.write_bytes((FIXTURES / "heading137_lat60_125hz.bin").read_bytes())
    (folder / "b_copy.bin").write_bytes(good.read_bytes())
    (folder / "c.json").write_text('{"schema": "calibd.result/6"}')
    (folder / "d.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(4000))
    (folder / "e.bin").symlink_to(folder / "nowhere.bin")
    (folder / "a.bin.truth.json").write_text("{}")  # a sidecar: not an input
    os.mkfifo(folder / "f.fifo")
    done = batch(folder, "-o", tmp_path / "t.parquet", "--workers", "1", timeout=120)
    assert done.returncode == 0, done.stderr
    rows = {Path(r["capture"]).name: r for r in fleettable.read_rows(tmp_path / "t.parquet")}
    assert set(rows) == {"a.bin", "b_copy.bin", "c.json", "d.png", "e.bin", "f.fifo"}
    assert rows["a.bin"]["status"] == "ok"
    assert rows["b_copy.bin"]["status"] == "duplicate" and "the same bytes as" in rows["b_copy.bin"]["error"]
    for name in ("c.json", "d.png"):
        assert rows[name]["status"] == "failed" and "no STIM300 datagram" in rows[name]["error"]
    assert rows["e.bin"]["status"] == "failed" and "No such file" in rows["e.bin"]["error"]
    assert rows["f.fifo"]["status"] == "failed" and "not a regular file" in rows["f.fifo"]["error"]
    assert all("\n" not in (r["error"] or "") for r in rows.values())


@pytest.mark.parametrize("scheduler, words", [
    ("nonsense://host:1", "unknown address scheme 'nonsense'"),
    ("host-without-port", "missing port number"),
    ("not-json", "not a Dask scheduler file"),
])
def test_a_bad_scheduler_is_one_line(run_main, tmp_path, scheduler, words):
    (tmp_path / "not-json").write_text("hello")
    where = tmp_path / scheduler if scheduler == "not-json" else scheduler
    code, out, err = run_main(calibd_main, ["batch", FIXTURES / "faults_125hz.bin", "-o", tmp_path / "t.parquet",
                                            "--scheduler", where, *SITE])
    assert code == 2 and err.count("\n") == 1 and f"--scheduler {where}" in err and words in err
    assert not (tmp_path / "t.parquet").exists()


@pytest.mark.slow
def test_a_scheduler_nobody_runs_is_one_line_after_the_timeout(run_main, tmp_path):
    code, out, err = run_main(calibd_main, ["batch", FIXTURES / "faults_125hz.bin", "-o", tmp_path / "t.parquet",
                                            "--scheduler", "tcp://127.0.0.1:9", *SITE])
    assert code == 2 and err.count("\n") == 1 and "--scheduler tcp://127.0.0.1:9: cannot connect" in err


@pytest.mark.parametrize("args, words", [
    (["--workers", "2", "--scheduler", "tcp://127.0.0.1:9"], "--workers sizes the local cluster"),
    (["--alpha", "0.5"], "give both --alpha and --beta"),
    (["--method", "thesis", "--drift"], "--drift belong to --method joint"),
    (["--workers", "0"], "--workers"),
])
def test_bad_options_are_one_line(run_main, tmp_path, args, words):
    code, out, err = run_main(calibd_main, ["batch", FIXTURES / "faults_125hz.bin", "-o", tmp_path / "t.parquet",
                                            *args, *SITE])
    assert code == 2 and err.count("\n") == 1 and words in err


def test_an_output_that_is_an_input_is_refused(run_main):
    capture = FIXTURES / "faults_125hz.bin"
    code, out, err = run_main(calibd_main, ["batch", capture, "-o", capture, *SITE])
    assert code == 2 and err.count("\n") == 1


def test_folders_are_walked_without_sidecars_or_hidden_files(tmp_path):
    for name in ("b.bin", "a.bin", "a.bin.truth.json", "a.bin.reads.npy", ".hidden.bin", "sub/c.bin",
                 ".git/d.bin"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(b"x")
    assert capture_paths([str(tmp_path), "given.bin"]) == [
        str(tmp_path / "a.bin"), str(tmp_path / "b.bin"), str(tmp_path / "sub" / "c.bin"), "given.bin"]


def test_the_plan_skips_what_the_table_has_and_names_duplicates(tmp_path):
    a, b, c = (tmp_path / n for n in ("a.bin", "b.bin", "c.bin"))
    a.write_bytes(b"one")
    b.write_bytes(b"one")
    c.write_bytes(b"two")
    first = plan([str(a), str(b), str(c)], SETTINGS, [], redo=False)
    assert [j.path for j in first.jobs] == [str(a), str(c)] and first.duplicates == 1
    assert first.rows[0]["status"] == "duplicate" and str(a) in first.rows[0]["error"]
    done = [first.jobs[0].base_row() | {"status": "ok"}, first.jobs[1].base_row() | {"status": "failed"}]
    second = plan([str(a), str(c)], SETTINGS, done, redo=False)
    assert [j.path for j in second.jobs] == [str(c)] and second.skipped == 1  # a failure is tried again
    other = BatchSettings("joint", Site(10.0))
    assert len(plan([str(a)], other, done, redo=False).jobs) == 1  # other settings: not the same calibration
    assert len(plan([str(a)], SETTINGS, done, redo=True).jobs) == 1


def test_a_new_row_replaces_the_old_rows_of_its_capture(tmp_path):
    def row(path, sha, status="ok", version="1", settings="s", power_up=1):
        return {"capture": path, "capture_sha256": sha, "status": status, "calibd_version": version,
                "settings": settings, "power_up": power_up}
    old = [row("a", "x"), row("a", "x", power_up=2), row("b", None, "failed"), row("c", "y"),
           row("a", "x", version="0"), row("d", "old")]
    new = [row("a", "x"), row("b", "z"), row("d", "new")]
    kept = merged(old, new)
    assert row("a", "x", version="0") in kept and row("c", "y") in kept  # another version; another capture
    assert row("d", "old") in kept  # the file at that path changed: both stay
    assert row("a", "x", power_up=2) not in kept and row("b", None, "failed") not in kept
    assert kept[-3:] == new


def test_the_settings_text_is_canonical():
    assert SETTINGS.text() == BatchSettings("joint", Site(float(LATITUDE), 0.0, float(G0)), {}).text()
    assert json.loads(SETTINGS.text())["latitude_deg"] == float(LATITUDE)


def test_a_table_round_trips_and_bad_tables_are_one_line(tmp_path):
    path = tmp_path / "t.parquet"
    rows = [fleettable.file_row("b.bin", "{}", "1", "ab", 3, 1.7e9) | {"status": "failed", "error": "no"},
            fleettable.file_row("a.bin", "{}", "1", "cd", 3, 1.7e9) | {"status": "ok", "power_up": 1, "yaw": 1.5}]
    fleettable.write_table(path, rows)
    back = fleettable.read_rows(path)
    assert [r["capture"] for r in back] == ["a.bin", "b.bin"] and back[0]["yaw"] == 1.5
    assert back[1]["capture_time"].timestamp() == 1.7e9
    not_a_table = tmp_path / "x.parquet"
    not_a_table.write_text("hello")
    with pytest.raises(fleettable.FleetError, match="x.parquet: not a fleet table"):
        fleettable.read_rows(not_a_table)
    import pyarrow
    import pyarrow.parquet

    data = pyarrow.parquet.read_table(path)
    newer = tmp_path / "newer.parquet"
    pyarrow.parquet.write_table(data.replace_schema_metadata({"calibd.schema": "calibd.fleet/9"}), newer)
    with pytest.raises(fleettable.FleetError, match="newer"):
        fleettable.read_rows(newer)
    other = tmp_path / "other.parquet"
    pyarrow.parquet.write_table(pyarrow.table({"a": [1]}), other)
    with pytest.raises(fleettable.FleetError, match="not a calibd.fleet file"):
        fleettable.read_rows(other)
    short = tmp_path / "short.parquet"
    pyarrow.parquet.write_table(data.drop_columns(["yaw"]), short)
    with pytest.raises(fleettable.FleetError, match="without column 'yaw'"):
        fleettable.read_rows(short)
    with pytest.raises(fleettable.FleetError, match="no such file"):
        fleettable.read_rows(tmp_path / "missing.parquet")


def test_progress_is_a_line_at_most_every_ten_seconds():
    import io

    from calibd.batch import Progress, Tally

    out = io.StringIO()
    progress, tally = Progress(out), Tally(total=3)
    for _ in range(3):
        tally.count([{"status": "ok"}])
        progress.show(tally)
    progress.show(tally, final=True)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("batch: 1/3 captures done") and lines[-1].startswith("batch: 3/3 captures done")
    assert len(lines) == 2


@pytest.mark.parametrize("package", ["distributed", "pyarrow"])
def test_without_the_fleet_extra_a_batch_is_one_line(run_main, tmp_path, monkeypatch, package):
    for module in [m for m in sys.modules if m.split(".")[0] == package]:
        monkeypatch.delitem(sys.modules, module)
    monkeypatch.setitem(sys.modules, package, None)
    code, out, err = run_main(calibd_main, ["batch", FIXTURES / "faults_125hz.bin", "-o", tmp_path / "t.parquet",
                                            "--workers", "1", *SITE])
    assert code == 2 and err.count("\n") == 1 and "pip install 'stim300-calib[fleet]'" in err


@pytest.mark.slow
def test_a_capture_with_a_restart_and_garbage_is_a_row_per_power_up(tmp_path):
    """faults_125hz: garbage, CRC errors, lost datagrams and a sensor restart, one minute of
    statics: each power-up is its own row, refused in the method's words, never a crash."""
    done = batch(FIXTURES / "faults_125hz.bin", "-o", tmp_path / "t.parquet", "--workers", "1", timeout=120)
    assert done.returncode == 0, done.stderr
    rows = fleettable.read_rows(tmp_path / "t.parquet")
    assert [(r["power_up"], r["power_ups"], r["status"]) for r in rows] == [(1, 2, "refused"), (2, 2, "refused")]
    assert all(r["error"].startswith(f"power-up {r['power_up']} of 2: not the joint method's") for r in rows)
    assert {r["serial_number"] for r in rows} == {"N25582405002002"}
