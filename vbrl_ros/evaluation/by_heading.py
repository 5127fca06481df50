"""Recall@1 split by how each revisit came back: the same way, turned, or reversed.

A mast's hidden wedge, an operator's body or a narrow field of view cost a method the revisits
driven the other way, and a lane change costs those most; one Recall@1 over all revisits hides
which. Each revisit query is classed by the heading between it and its nearest visible database
keyframe within the radius (the ground truth's poses), and Recall@1 is counted per class.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vbrl_ros.evaluation.metrics import correct_mask, online_database_limits, revisit_mask

#: (name, from, to) in degrees of heading between a revisit and its nearest earlier pass.
HEADING_CLASSES = (("same way", 0.0, 45.0), ("turned", 45.0, 135.0), ("reversed", 135.0, 180.0))


@dataclass(frozen=True)
class HeadingRecall:
    """Per heading class (:data:`HEADING_CLASSES`): revisit queries and those whose top-1 is right."""

    revisits: dict[str, int]
    hits: dict[str, int]

    def recall(self, name: str) -> float:
        return self.hits[name] / self.revisits[name] if self.revisits[name] else math.nan

    def summary(self) -> dict[str, dict[str, float | int]]:
        return {name: {"revisits": self.revisits[name], "hits": self.hits[name], "recall_at_1": self.recall(name)}
                for name, _, _ in HEADING_CLASSES}


def horizontal_headings(poses: np.ndarray) -> np.ndarray:
    """(n,) radians: the direction of each sensor's x axis (4x4 T_world_lidar) on the ground plane."""
    poses = np.asarray(poses, dtype=np.float64)
    return np.arctan2(poses[:, 1, 0], poses[:, 0, 0])


def heading_classes(query_poses: np.ndarray, database_poses: np.ndarray, radius: float,
                    database_limit: np.ndarray | None = None) -> np.ndarray:
    """(n_query,) int: the :data:`HEADING_CLASSES` index of each revisit query (its heading to the
    nearest visible database keyframe within ``radius``), -1 for a query that is no revisit."""
    q, db = np.asarray(query_poses, np.float64), np.asarray(database_poses, np.float64)
    limits = np.full(len(q), len(db)) if database_limit is None else np.asarray(database_limit, np.int64)
    revisit = revisit_mask(q[:, :3, 3], db[:, :3, 3], radius, limits)
    query_heading, database_heading = horizontal_headings(q), horizontal_headings(db)
    edges = np.array([upper for _, _, upper in HEADING_CLASSES[:-1]])
    out = np.full(len(q), -1, np.int64)
    for i in np.flatnonzero(revisit):
        distances = np.linalg.norm(db[:limits[i], :3, 3] - q[i, :3, 3], axis=1)
        nearest = int(np.argmin(distances))
        turn = abs(math.remainder(query_heading[i] - database_heading[nearest], 2.0 * math.pi))
        out[i] = int(np.searchsorted(edges, math.degrees(turn), side="right"))
    return out


def recall_by_heading(query_poses: np.ndarray, database_poses: np.ndarray, indices: np.ndarray, radius: float,
                      database_limit: np.ndarray | None = None) -> HeadingRecall:
    """Recall@1 of the top-K ``indices`` (n_query, K) per heading class at ``radius``; P1 passes
    its visible prefixes as ``database_limit``, P2 the queries' poses in the database's frame."""
    classes = heading_classes(query_poses, database_poses, radius, database_limit)
    q, db = np.asarray(query_poses)[:, :3, 3], np.asarray(database_poses)[:, :3, 3]
    right = correct_mask(q, db, np.atleast_2d(indices)[:, :1], radius, database_limit)[:, 0]
    revisits = {name: int((classes == k).sum()) for k, (name, _, _) in enumerate(HEADING_CLASSES)}
    hits = {name: int((right & (classes == k)).sum()) for k, (name, _, _) in enumerate(HEADING_CLASSES)}
    return HeadingRecall(revisits, hits)


def format_heading_recall(by_method: dict[str, HeadingRecall], radius: float) -> str:
    """The table ``vbrl eval`` prints: per method, right top-1 / revisits of each heading class."""
    header = "  ".join(f"{f'{name} ({low:g}-{high:g} deg)':>24}" for name, low, high in HEADING_CLASSES)
    lines = [f"Recall@1 by heading to the nearest earlier pass, radius {radius:g} m",
             f"  {'method':<24} {header}"]
    for method, recall in by_method.items():
        cells = "  ".join(f"{f'{recall.hits[n]}/{recall.revisits[n]}':>24}" for n, _, _ in HEADING_CLASSES)
        lines.append(f"  {method:<24} {cells}")
    return "\n".join(lines)


def recalls_by_heading(indices_by_method: dict[str, np.ndarray], query_poses: np.ndarray | None,
                       database_poses: np.ndarray | None, radius: float, *, exclude: int | None = None,
                       alignment: np.ndarray | None = None) -> dict[str, HeadingRecall] | None:
    """:func:`recall_by_heading` of every method's top-K: P1 (``exclude`` given) against each
    query's visible prefix, P2 with the queries' poses taken into the database's frame by
    ``alignment`` (T_A<-B). None without poses."""
    if query_poses is None or database_poses is None:
        return None
    query_poses = np.asarray(query_poses, np.float64)
    if alignment is not None:
        query_poses = np.asarray(alignment, np.float64) @ query_poses
    limit = None if exclude is None else online_database_limits(len(query_poses), exclude)
    return {name: recall_by_heading(query_poses, database_poses, indices, radius, limit)
            for name, indices in indices_by_method.items()}
