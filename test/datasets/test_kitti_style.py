"""KITTI-style folders: write_kitti_style -> KittiStyleSource round trip, bad folders, the shared recordings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vbrl_ros.datasets import detect_source_kind, open_source
from vbrl_ros.datasets.base import Scan, ScanSourceError
from vbrl_ros.datasets.kitti_style import KittiStyleSource, write_kitti_style

SHARED_DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


def make_poses(count: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", np.linspace(0, 3, count)[:, None]).as_matrix()
    poses[:, :3, 3] = np.column_stack([np.arange(count), np.arange(count) ** 2 * 0.1, np.full(count, 0.5)])
    return poses


def make_scans(count: int) -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    return [rng.normal(0, 5, size=(50 + i, 4)).astype(np.float32) for i in range(count)]


def test_write_then_read_round_trips(tmp_path: Path) -> None:
    scans, poses, stamps = make_scans(12), make_poses(12), 1_630_577_758.5 + np.arange(12) * 0.1
    scans[4][0, 1] = np.inf
    scans[4][1, :3] = 0.0  # a no-return placeholder
    folder = write_kitti_style(tmp_path / "run", (s for s in scans), poses, stamps)
    assert sorted(p.name for p in folder.iterdir()) == ["poses.txt", "times.txt", "velodyne"]
    assert (folder / "velodyne" / "000011.bin").stat().st_size == 61 * 16
    assert detect_source_kind(folder) == "kitti_style"
    source = KittiStyleSource(folder)
    assert len(source) == 12 and source.name == "run"
    np.testing.assert_allclose(source.poses, poses, atol=1e-9)
    np.testing.assert_allclose(source.stamps, stamps, atol=1e-6)
    for index in (0, 10, 11, 4):  # numeric order: 000010 after 000009
        scan = source[index]
        returns = np.isfinite(scans[index][:, :3]).all(axis=1) & (scans[index][:, :3] != 0).any(axis=1)
        expected = scans[index][returns].astype(np.float64)
        np.testing.assert_array_equal(scan.points, expected[:, :3])
        np.testing.assert_array_equal(scan.intensity, expected[:, 3])
        assert scan.index == index and scan.stamp == pytest.approx(stamps[index])
    assert len(source[4].points) == 52
    assert [s.index for s in source] == list(range(12))


def test_optional_files_and_scan_forms(tmp_path: Path) -> None:
    scans = [np.ones((4, 3)), Scan(np.zeros((2, 3)), None, 0.0, 0), Scan(np.ones((1, 3)), np.array([9.0]), 0.0, 1)]
    folder = write_kitti_style(tmp_path / "bare", scans, None)
    source = open_source(folder)
    assert source.poses is None
    np.testing.assert_array_equal(source.stamps, [0.0, 1.0, 2.0])  # no times.txt: the index
    np.testing.assert_array_equal(source[0].intensity, np.zeros(4))
    np.testing.assert_array_equal(source[2].intensity, [9.0])


def test_failed_write_leaves_nothing(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="got 3 scans but 4 poses"):
        write_kitti_style(tmp_path / "run", make_scans(3), make_poses(4))
    with pytest.raises(ValueError, match=r"scan 1 has shape \(5,\)"):
        write_kitti_style(tmp_path / "run", [np.zeros((5, 4)), np.zeros(5)], None)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("precious")
    with pytest.raises(FileExistsError):
        write_kitti_style(tmp_path / "full", make_scans(1), None)
    assert (tmp_path / "full" / "keep.txt").read_text() == "precious"
    (tmp_path / "empty").mkdir()
    assert len(KittiStyleSource(write_kitti_style(tmp_path / "empty", make_scans(2), None))) == 2


def test_malformed_folders_are_clear_errors(tmp_path: Path) -> None:
    folder = write_kitti_style(tmp_path / "run", make_scans(3), make_poses(3), np.arange(3.0))
    (folder / "times.txt").write_text("1\n2\n")
    with pytest.raises(ScanSourceError, match="2 stamps for 3 scans"):
        KittiStyleSource(folder)
    (folder / "times.txt").unlink()
    (folder / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(ScanSourceError, match="expected 3 poses"):
        KittiStyleSource(folder)
    (folder / "poses.txt").unlink()
    (folder / "velodyne" / "000001.bin").write_bytes(b"\x00" * 20)
    with pytest.raises(ScanSourceError, match="000001.bin: 20 bytes"):
        KittiStyleSource(folder)[1]
    with pytest.raises(ScanSourceError, match="no velodyne/"):
        KittiStyleSource(tmp_path)


@pytest.mark.skipif(not SHARED_DATA.is_dir(), reason="shared recordings (../shared/data) not present")
@pytest.mark.parametrize(("name", "count"), [("balm_realworld", 177), ("mid360_walk", 1119)])
def test_shared_recordings(name: str, count: int) -> None:
    folder = SHARED_DATA / name
    if not folder.is_dir():
        pytest.skip(f"{folder} not present")
    source = open_source(folder)
    assert len(source) == count and source.poses.shape == (count, 4, 4)
    assert np.all(np.diff(source.stamps) > 0) and source.stamps[0] > 1.6e9
    rotations = source.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ np.swapaxes(rotations, 1, 2), np.broadcast_to(np.eye(3), rotations.shape),
                               atol=1e-4)
    for scan in (source[0], source[-1]):
        assert len(scan.points) > 1000 and np.isfinite(scan.points).all() and scan.intensity.shape == (len(scan.points),)
    # Scans are in the sensor frame: their centroid is near the sensor, not the world origin of far-away scans.
    assert np.linalg.norm(np.median(source[-1].points, axis=0)) < 30.0
