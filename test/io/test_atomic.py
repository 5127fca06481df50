import os
import stat

import pytest

from vbrl_ros.io.atomic import atomic_write


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
