"""The daemon's [record] table: the sensor's bytes and samples into rotating MCAP files
(`calibd.serve.recorder`, through the hub's tap as `calibd run` and `calibd replay --serve`
use it): together the files hold every byte once, in order; each is whole and read as a capture;
the newest `keep` are kept; bad tables and a missing directory or extra are one line."""

import sys
from pathlib import Path

import pytest

from calibd.config import RecordConfig, load_config
from calibd.serve.recorder import Recorder
from calibd.serve.sockets import ServeError
from captures import calibd
from stim300.mcaprec import read_capture

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
CAPTURE = FIXTURES / "static_turn_2000hz.bin"  # 15.5 s at 2000 Hz, 1.9 MB


def config(tmp_path: Path, record: str) -> Path:
    path = tmp_path / "calibd.toml"
    path.write_text(f'[serial]\nport = "/dev/null"\n[site]\nlatitude_deg = 40.6\n[output]\nstate_dir = "{tmp_path}"\n'
                    f"[record]\n{record}\n")
    return path


def replay(tmp_path: Path, record: str):
    run = calibd("replay", CAPTURE, "--config", config(tmp_path, record), "--serve", "--speed", "max")
    out, err = run.communicate(timeout=120)
    return run.returncode, err.decode()


@pytest.mark.slow
def test_the_files_hold_every_byte_once_and_each_is_a_capture(tmp_path):
    folder = tmp_path / "rec"
    folder.mkdir()
    code, err = replay(tmp_path, f'directory = "{folder}"\nrotate_mb = 1\nkeep = 0')
    files = sorted(folder.iterdir())
    assert files and all(f.name.startswith("stim300-") and f.suffix == ".mcap" for f in files), files
    assert len(files) >= 3  # 1.9 MB of bytes and their Imu messages, about 1 MB a file
    held = [read_capture(f) for f in files]
    assert b"".join(data for data, _ in held) == CAPTURE.read_bytes()
    times = [t for _, reads in held for t in reads["t_host_s"]]
    assert times == sorted(times)


@pytest.mark.slow
def test_only_the_newest_files_are_kept(tmp_path):
    folder = tmp_path / "rec"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    code, err = replay(tmp_path, f'directory = "{folder}"\nrotate_mb = 1\nkeep = 2')
    names = sorted(p.name for p in folder.iterdir())
    assert len(names) == 3 and "notes.txt" in names
    data = b"".join(read_capture(folder / n)[0] for n in names if n.endswith(".mcap"))
    assert CAPTURE.read_bytes().endswith(data)  # the last two files: the end of the stream


@pytest.mark.parametrize("record, says", [
    ("rotate_s = 600", "[record] directory: missing"),
    ('directory = "{d}"\nrotate_s = 10', "[record] rotate_s: 10.0 is not a duration in [60, 604800] s"),
    ('directory = "{d}"\nkeep = -1', "[record] keep"),
    ('directory = "{d}"\nframe_id = "imu link"', "[record] frame_id"),
    ('directory = "{d}"\nrotate = 5', "[record] rotate: unknown key"),
])
def test_a_bad_record_table_is_one_line(tmp_path, record, says):
    from calibd.config import ConfigError

    with pytest.raises(ConfigError) as caught:
        load_config(config(tmp_path, record.replace("{d}", str(tmp_path))))
    assert says in str(caught.value) and "\n" not in str(caught.value)


def test_a_directory_that_cannot_take_recordings_is_refused_before_start(tmp_path):
    file = tmp_path / "file"
    file.write_text("")
    Recorder(RecordConfig(tmp_path / "made")).close()  # made when its parent exists
    assert (tmp_path / "made").is_dir()
    for directory, says in ((tmp_path / "no" / "parent", "cannot be made"), (file, "not a directory")):
        with pytest.raises(ServeError, match=f"\\[record\\] directory {directory}: {says}"):
            Recorder(RecordConfig(directory))
    code, err = replay(tmp_path, f'directory = "{tmp_path / "no" / "parent"}"')
    assert code == 1 and err.strip().count("\n") == 0 and "[record] directory" in err


def test_without_the_recordings_extra_it_is_one_line(tmp_path, monkeypatch):
    for module in [m for m in sys.modules if m.split(".")[0] == "mcap"]:
        monkeypatch.delitem(sys.modules, module)
    monkeypatch.setitem(sys.modules, "mcap", None)
    with pytest.raises(ServeError, match=r"\[record\] .*pip install 'stim300-calib\[recordings\]'"):
        Recorder(RecordConfig(tmp_path))
