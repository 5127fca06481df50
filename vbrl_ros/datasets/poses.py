"""Per-scan poses T_world_lidar: from a bag, a poses.txt, or KISS-ICP odometry.

Pose specs (``resolve_poses`` / ``open_source(poses=...)``):

* ``"auto"`` - the poses the data itself carries: a folder's ``poses.txt``
  (KITTI-style) or ground truth (KITTI odometry); for a bag, its only
  ``nav_msgs/Odometry`` topic, else its only ``PoseStamped`` /
  ``PoseWithCovarianceStamped`` topic (several candidates: an error listing
  them). None when the data has no poses - KISS-ICP is never run implicitly.
* ``"odom:/topic"`` / ``"pose:/topic"`` - a bag topic of any of those pose
  types, the pose of the LiDAR frame; Odometry of another frame (its
  ``child_frame_id`` a robot's ``base_link``, not the clouds' ``frame_id``)
  is carried over to the LiDAR by the bag's tf, and a warning says so when
  the tf does not connect the two.
* ``"tf:parent:child"`` - chain ``/tf`` + ``/tf_static`` from frame
  ``parent`` (the world) to frame ``child`` (the LiDAR).
* ``"file:/path/poses.txt"`` - 12 numbers a line, one line per scan.
* ``"kiss-icp"`` - estimate with KISS-ICP odometry (world = first scan).
* ``"none"``.

Recorded poses are interpolated to the scan stamps: SLERP for rotation,
linear for translation. A scan outside the recorded time range is not
extrapolated: its pose is NaN (all 16 entries) and one warning says how many
scans that hit, so no scan is lost and no pose is invented.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation, Slerp
from tqdm import tqdm

if TYPE_CHECKING:
    from vbrl_ros.datasets.base import Scan, ScanSource


class PoseSourceError(ValueError):
    """Poses cannot be obtained as asked (bad spec, missing topic/frames, wrong count)."""


class OutsidePoseRangeWarning(UserWarning):
    """Some scans lie outside the time range of the recorded poses; their poses are NaN."""


class OdometryFrameWarning(UserWarning):
    """Odometry moves another frame than the clouds' and the bag's tf does not connect the two."""


# --------------------------------------------------------------------------- poses.txt


def read_poses_txt(path: str | Path) -> np.ndarray:
    """(n, 4, 4) poses from a KITTI poses file (12 numbers a line: row-major 3x4)."""
    try:
        values = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as error:
        raise PoseSourceError(f"{path}: not 12 numbers per line ({error})") from None
    if values.size == 0:
        return np.zeros((0, 4, 4))
    if values.shape[1] != 12:
        raise PoseSourceError(f"{path}: {values.shape[1]} numbers per line, expected 12 (row-major 3x4)")
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :] = values.reshape(-1, 3, 4)
    return poses


def write_poses_txt(path: str | Path, poses: np.ndarray) -> None:
    """Write (n, 4, 4) poses as a KITTI poses file (9 decimals: sub-nanometre, sub-nanoradian)."""
    poses = np.asarray(poses, dtype=np.float64)
    np.savetxt(path, poses[:, :3, :].reshape(-1, 12), fmt="%.9f")


# --------------------------------------------------------------------------- interpolation


def _sorted_unique(stamps: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort by time; of samples with equal stamps keep the last one recorded."""
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], poses[order]
    keep = np.append(np.diff(stamps) > 0, True)
    return stamps[keep], poses[keep]


def interpolate_poses(sample_stamps: np.ndarray, sample_poses: np.ndarray, query_stamps: np.ndarray, *,
                      label: str = "poses", warn: bool = True) -> np.ndarray:
    """Poses at ``query_stamps`` from timed samples (SLERP rotation, linear translation).

    Queries outside [first, last] sample stamp get NaN poses (and, when
    ``warn``, one OutsidePoseRangeWarning naming ``label``).
    """
    sample_stamps = np.asarray(sample_stamps, dtype=np.float64).reshape(-1)
    sample_poses = np.asarray(sample_poses, dtype=np.float64).reshape(-1, 4, 4)
    query_stamps = np.asarray(query_stamps, dtype=np.float64).reshape(-1)
    if len(sample_stamps) != len(sample_poses):
        raise PoseSourceError(f"{label}: {len(sample_stamps)} stamps for {len(sample_poses)} poses")
    result = np.full((len(query_stamps), 4, 4), np.nan)
    if len(sample_stamps):
        stamps, poses = _sorted_unique(sample_stamps, sample_poses)
        inside = (query_stamps >= stamps[0]) & (query_stamps <= stamps[-1])
        if len(stamps) == 1:
            result[inside] = poses[0]
        elif inside.any():
            times = query_stamps[inside]
            rotations = Slerp(stamps, Rotation.from_matrix(poses[:, :3, :3]))(times)
            block = np.tile(np.eye(4), (len(times), 1, 1))
            block[:, :3, :3] = rotations.as_matrix()
            block[:, :3, 3] = np.column_stack([np.interp(times, stamps, poses[:, axis, 3]) for axis in range(3)])
            result[inside] = block
    outside = int(np.isnan(result[:, 0, 0]).sum())
    if warn and outside:
        span = f"[{sample_stamps.min():.3f}, {sample_stamps.max():.3f}] s" if len(sample_stamps) else "(no samples)"
        warnings.warn(f"{label}: {outside} of {len(query_stamps)} scans lie outside the pose time range {span}; "
                      "their poses are NaN", OutsidePoseRangeWarning, stacklevel=2)
    return result


def invert_transforms(transforms: np.ndarray) -> np.ndarray:
    """Inverse of rigid (..., 4, 4) transforms, [R t]^-1 = [R^T -R^T t]; NaN stays NaN."""
    rotation_t = np.swapaxes(transforms[..., :3, :3], -1, -2)
    inverse = np.zeros_like(transforms)
    inverse[..., :3, :3] = rotation_t
    inverse[..., :3, 3] = -(rotation_t @ transforms[..., :3, 3:4])[..., 0]
    inverse[..., 3, 3] = 1.0
    return inverse


def chain_tf(edges: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, bool]], parent: str, child: str,
             query_stamps: np.ndarray, *, label: str = "tf") -> np.ndarray:
    """T_parent_child at each query stamp, chaining tf edges (parent, child) -> (stamps, T, static).

    The path may go up and down the tree (e.g. map -> odom -> base <- lidar
    is walked as map->odom->base->lidar with the last edge inverted). Static
    edges hold at all times; dynamic ones are interpolated, NaN outside their
    time range (one warning for all).
    """
    parent, child = parent.lstrip("/"), child.lstrip("/")
    neighbours: dict[str, list[tuple[str, tuple[str, str], bool]]] = {}
    for a, b in edges:
        neighbours.setdefault(a, []).append((b, (a, b), True))
        neighbours.setdefault(b, []).append((a, (a, b), False))
    for frame in (parent, child):
        if frame not in neighbours:
            raise PoseSourceError(f"{label}: no frame '{frame}' (frames: {', '.join(sorted(neighbours)) or 'none'})")
    previous: dict[str, tuple[str, tuple[str, str], bool] | None] = {parent: None}
    frontier = [parent]
    while frontier and child not in previous:
        next_frontier = []
        for frame in frontier:
            for other, edge, forward in neighbours[frame]:
                if other not in previous:
                    previous[other] = (frame, edge, forward)
                    next_frontier.append(other)
        frontier = next_frontier
    if child not in previous:
        raise PoseSourceError(f"{label}: frames '{parent}' and '{child}' are not connected by tf")
    hops = []
    frame = child
    while (step := previous[frame]) is not None:
        hops.append(step)
        frame = step[0]
    query_stamps = np.asarray(query_stamps, dtype=np.float64).reshape(-1)
    result = np.tile(np.eye(4), (len(query_stamps), 1, 1))
    for _, edge, forward in reversed(hops):
        stamps, transforms, static = edges[edge]
        if static:
            hop = np.broadcast_to(transforms[np.argmax(stamps)], result.shape)
        else:
            hop = interpolate_poses(stamps, transforms, query_stamps, warn=False)
        result = result @ (hop if forward else invert_transforms(hop))
    outside = int(np.isnan(result[:, 0, 0]).sum())
    if outside:
        warnings.warn(f"{label} {parent}->{child}: {outside} of {len(query_stamps)} scans lie outside the time "
                      "range of the tf data; their poses are NaN", OutsidePoseRangeWarning, stacklevel=2)
    return result


# --------------------------------------------------------------------------- KISS-ICP


def estimate_poses_kiss_icp(scans: Iterable[Scan], count: int | None = None, *, config: Any = None,
                            max_range: float = 100.0, min_range: float = 0.0, voxel_size: float | None = None,
                            progress: bool = True) -> np.ndarray:
    """T_world_lidar per scan from KISS-ICP odometry (world = the first scan's frame).

    Without ``config`` a ``kiss_icp.config.KISSConfig`` is built from
    ``max_range``/``min_range``/``voxel_size`` (default max_range / 100, as
    kiss_icp does) with deskewing off: scans carry no per-point times.
    """
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    if config is None:
        config = KISSConfig()
        config.data.max_range, config.data.min_range, config.data.deskew = max_range, min_range, False
        config.mapping.voxel_size = voxel_size if voxel_size is not None else max_range / 100.0
    odometry = KissICP(config)
    no_times = np.zeros(0, dtype=np.float64)
    poses = []
    for scan in tqdm(scans, total=count, desc="KISS-ICP odometry", unit="scan", disable=not progress):
        odometry.register_frame(np.ascontiguousarray(scan.points, dtype=np.float64), no_times)
        poses.append(odometry.last_pose.copy())
    return np.array(poses).reshape(-1, 4, 4)


# --------------------------------------------------------------------------- spec resolution


class PoseSpec(NamedTuple):
    kind: str  # auto | none | kiss-icp | odom | pose | tf | file
    topic: str | None = None
    parent: str | None = None
    child: str | None = None
    path: Path | None = None


def parse_pose_spec(spec: str | None) -> PoseSpec:
    if spec is None or spec in ("none", ""):
        return PoseSpec("none")
    if spec in ("auto", "kiss-icp"):
        return PoseSpec(spec)
    kind, _, rest = spec.partition(":")
    if kind in ("odom", "pose") and rest:
        return PoseSpec(kind, topic=rest)
    if kind == "tf" and rest.count(":") == 1 and all(rest.split(":")):
        parent, child = rest.split(":")
        return PoseSpec("tf", parent=parent, child=child)
    if kind == "file" and rest:
        return PoseSpec("file", path=Path(rest))
    raise PoseSourceError(f"unknown pose spec {spec!r}; use auto, none, kiss-icp, odom:/topic, pose:/topic, "
                          "tf:parent:child or file:/path/poses.txt")


def _bag_auto_topic(source: Any) -> str | None:
    from vbrl_ros.datasets.rosbag import POSE_GETTERS

    odometry = source.topics_of_type("nav_msgs/msg/Odometry")
    stamped = source.topics_of_type(*(t for t in POSE_GETTERS if t != "nav_msgs/msg/Odometry"))
    for candidates in (odometry, stamped):
        if len(candidates) == 1:
            return candidates[0]
        if candidates:
            raise PoseSourceError(f"{source.name}: several pose topics, choose one with poses='odom:<topic>': "
                                  f"{', '.join(candidates)}")
    return None


def resolve_poses(source: ScanSource, spec: str | None = "auto", *, progress: bool = True,
                  **kiss_icp_options: Any) -> np.ndarray | None:
    """(n, 4, 4) T_world_lidar for every scan of ``source`` per ``spec`` (see module docstring), or None."""
    from vbrl_ros.datasets.rosbag import RosbagSource

    parsed = parse_pose_spec(spec)
    is_bag = isinstance(source, RosbagSource)
    if parsed.kind in ("odom", "pose", "tf") and not is_bag:
        raise PoseSourceError(f"pose spec {spec!r} needs a bag; {source.name} is a {type(source).__name__}")
    if parsed.kind == "none":
        return None
    if parsed.kind == "auto":
        if not is_bag:
            return source.poses
        topic = _bag_auto_topic(source)
        parsed = PoseSpec("odom", topic=topic) if topic else PoseSpec("none")
    if parsed.kind == "none":
        return None
    if parsed.kind == "kiss-icp":
        return estimate_poses_kiss_icp(iter(source), len(source), progress=progress, **kiss_icp_options)
    if parsed.kind == "file":
        poses = read_poses_txt(parsed.path)
        if len(poses) != len(source):
            raise PoseSourceError(f"{parsed.path}: {len(poses)} poses for {len(source)} scans of {source.name}")
        return poses
    if parsed.kind == "tf":
        return chain_tf(source.tf_samples(), parsed.parent, parsed.child, source.stamps, label=f"{source.name} tf")
    stamps, poses = source.pose_samples(parsed.topic)
    poses = interpolate_poses(stamps, poses, source.stamps, label=f"{source.name} {parsed.topic}")
    return carried_to_lidar(source, parsed.topic, poses)


def _other_frames(source: Any, topic: str) -> tuple[str, str] | None:
    """(the frame ``topic`` moves, the clouds' frame) when both are named and differ."""
    moved, lidar = source.moved_frame(topic), source.cloud_frame()
    return (moved, lidar) if moved and lidar and moved != lidar else None


def carried_to_lidar(source: Any, topic: str, poses: np.ndarray) -> np.ndarray:
    """``poses`` of an odometry topic as the LiDAR's: times the bag's tf from the frame the odometry
    moves (a robot's ``base_link``) to the clouds' frame, when the two differ. Submaps merged by
    base_link poses are smeared wherever the LiDAR is turned or tilted against it."""
    frames = _other_frames(source, topic)
    if frames is None:
        return poses
    moved, lidar = frames
    try:
        mounting = chain_tf(source.tf_samples(), moved, lidar, source.stamps, label=f"{source.name} tf")
    except PoseSourceError:
        warnings.warn(f"{source.name} {topic}: odometry moves frame '{moved}', the clouds are in '{lidar}', and "
                      f"the bag's tf does not connect them: its poses are taken as the LiDAR's",
                      OdometryFrameWarning, stacklevel=2)
        return poses
    return poses @ mounting


class Mounting(NamedTuple):
    """Where the clouds' frame sits in the frame an odometry topic moves, by a bag's tf."""

    moved: str
    lidar: str
    T_moved_lidar: np.ndarray | None  # None: the bag's tf does not connect the two


def lidar_mounting(source: Any, topic: str) -> Mounting | None:
    """The LiDAR's mounting in the frame ``topic``'s odometry moves, by the bag's static tf (a mount
    is fixed; robot_state_publisher sends it there); None when the odometry moves the clouds' own
    frame (or either does not say)."""
    frames = _other_frames(source, topic)
    if frames is None:
        return None
    moved, lidar = frames
    try:  # static edges hold at every time: never NaN
        T = chain_tf(source.tf_samples(static_only=True), moved, lidar, source.stamps[:1],
                     label=f"{source.name} tf_static")[0]
    except PoseSourceError:
        T = None
    return Mounting(moved, lidar, T)
