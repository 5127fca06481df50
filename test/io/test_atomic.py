import os
import signal
import stat
import subprocess
import sys

import pytest

from vbrl_ros.io.atomic import atomic_write, check_writable, remove_stale_temporaries


def test_replaces_the_file_and_respects_the_umask(tmp_path):
    target = tmp_path / "sub" / "file.bin"
    atomic_write(target, lambda f: f.write(b"one"))
    atomic_write(target, lambda f: f.write(b"two"))
    assert target.read_bytes() == b"two"
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~mask
    assert [p.name for p in target.parent.iterdir()] == ["file.bin"]


def test_a_crash_mid_write_keeps_the_last_good_copy(tmp_path):
    target = tmp_path / "file.bin"
    atomic_write(target, lambda f: f.write(b"good"))

    def crash(handle):
        handle.write(b"half")
        raise RuntimeError("power cut")

    with pytest.raises(RuntimeError):
        atomic_write(target, crash)
    assert target.read_bytes() == b"good"
    assert [p.name for p in tmp_path.iterdir()] == ["file.bin"]


WRITER = """
import sys, time
from vbrl_ros.io.atomic import atomic_write

def write(handle):
    handle.write(b"half a file")
    handle.flush()
    print("writing", flush=True)
    time.sleep(120)

atomic_write(sys.argv[1], write)
"""


def writer_mid_write(target):
    """A real process stopped inside atomic_write, its temporary file beside ``target``."""
    process = subprocess.Popen([sys.executable, "-c", WRITER, str(target)], stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "writing"
    return process


def kill_9(process):
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=10)


def temporaries(target):
    return sorted(target.parent.glob(f".{target.name}.*.tmp"))


def test_stale_temporaries_of_killed_writers_go_and_a_live_writers_stays(tmp_path):
    target = tmp_path / "keyframes.npz"
    atomic_write(target, lambda f: f.write(b"good"))
    other = tmp_path / ".keyframes_old.npz.abcd1234.tmp"  # another file's: never touched
    other.write_bytes(b"x")
    dead = [writer_mid_write(target) for _ in range(2)]
    for process in dead:
        kill_9(process)
    live = writer_mid_write(target)
    try:
        left = temporaries(target)
        assert len(left) == 3 and target.read_bytes() == b"good"
        removed = remove_stale_temporaries(target)
        assert len(removed) == 2 and temporaries(target) == sorted(set(left) - set(removed))
    finally:
        kill_9(live)
    assert len(remove_stale_temporaries(target)) == 1 and temporaries(target) == []
    assert target.read_bytes() == b"good" and other.exists()


def test_check_writable_makes_the_folders_and_names_what_is_in_the_way(tmp_path):
    check_writable(tmp_path / "new" / "deeper" / "file.npz")
    assert (tmp_path / "new" / "deeper").is_dir() and list((tmp_path / "new" / "deeper").iterdir()) == []
    (tmp_path / "afile").write_text("x")
    with pytest.raises(NotADirectoryError) as error:
        check_writable(tmp_path / "afile" / "sub" / "file.npz")
    assert (error.value.strerror, error.value.filename) == ("a file where a folder should be", str(tmp_path / "afile"))
    with pytest.raises(IsADirectoryError):
        check_writable(tmp_path / "new")
