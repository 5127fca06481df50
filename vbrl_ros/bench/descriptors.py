"""Realistic compact descriptors for the keyframe index's tests and benchmark.

Real geometry, not iid noise: a small simulated town driven twice (summer,
then winter from slightly offset spots), described by the package's own
featurizers and standardised.

- **Cartesian**: the shipped paper-configuration model (featurizer, standardisation, learned
  Eq. 4 weights; ``prune`` as in :meth:`VBRLModel.scorer`).
- **Polar** (S sectors, the paper model's layers and range): the polar
  featurizer; standardisation statistics are pooled over the drive and tied
  across sectors. No trained polar model ships yet (``vbrl bench
  --polar-model`` takes one, grid and all), so the stand-in's tied weights are
  the paper model's modality importances times its voxel importances
  averaged over each (layer, ring) annulus, with the least important third of
  the annuli switched off as the sparsity norms would. The winter
  drive's scans are rotated by seeded random yaws before they are described,
  so queries exercise the rotation search; the true relative yaw of every pair
  is known from the poses (:func:`relative_yaw`).

:func:`replicate` grows a few hundred real descriptors into databases of
100k keyframes in a second or two (the index's speed does not depend on the values,
its recall does — which is why the real ones are used for it too).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from vbrl_ros.model.scoring import WeightedL1Scorer, row_weights

SESSIONS = (("summer_clear", 1, 0.0), ("winter_snow", 2, 1.5))  # scenario, seed, offset (m)


@dataclass(frozen=True)
class DescriptorSet:
    """Compact standardised descriptors of a simulated two-session drive."""

    name: str
    descriptors: np.ndarray  # (n, d_active) float32, sector-major
    scorer: WeightedL1Scorer
    session: np.ndarray  # (n,) 0 = summer, 1 = winter (the rotated one for polar)
    poses: np.ndarray  # (n, 4, 4) T_world_lidar of the scan *as described*

    @property
    def weights(self) -> np.ndarray:
        return self.scorer.active_weights

    @property
    def sectors(self) -> int:
        return self.scorer.sectors


def simulated_scans(blocks: int = 1, loops: int = 1, beams: int = 32, columns: int = 900,
                    spacing_m: float = 2.0, seed: int = 3) -> list[tuple[np.ndarray, np.ndarray, int]]:
    """(points (N, 3) float32, T_world_lidar, session) of every scan of both drives."""
    import vbrl_ros.simulator as sim

    town = sim.generate_town(sim.TownConfig(blocks_x=blocks, blocks_y=blocks), seed=seed)
    scans = []
    for session, (scenario, run_seed, offset) in enumerate(SESSIONS):
        route = sim.make_route(town, sim.RouteConfig(loops=loops, spacing_m=spacing_m,
                                                     sample_offset_m=offset))
        run = sim.simulate_run(town, route, sim.LidarConfig(beams=beams, columns=columns),
                               scenario, seed=run_seed)
        for i in range(len(run)):
            scans.append((run.scan(i).points[:, :3].astype(np.float32), run.poses[i], session))
    return scans


def cartesian_set(scans: list[tuple[np.ndarray, np.ndarray, int]], prune: float = 0.0) -> DescriptorSet:
    """The paper model's compact descriptors of ``scans``."""
    from vbrl_ros.model.builtin import load_paper_model

    model = load_paper_model()
    scorer, featurizer = model.scorer(prune), model.featurizer()
    rows = [scorer.compact(model.standardize(featurizer.describe(p))) for p, _, _ in scans]
    return DescriptorSet("cartesian", np.asarray(rows, np.float32), scorer,
                         np.array([s for _, _, s in scans]), np.array([t for _, t, _ in scans]))


def polar_set(scans: list[tuple[np.ndarray, np.ndarray, int]], sectors: int = 24,
              off_fraction: float = 1 / 3, seed: int = 0, model: Any = None,
              prune: float = 0.0) -> DescriptorSet:
    """Polar-grid compact descriptors; the winter session is rotated by random yaws first.

    ``model``: a trained polar :class:`~vbrl_ros.model.model_file.VBRLModel` whose grid,
    standardisation and weights (pruned by ``prune``, as in
    :meth:`~vbrl_ros.model.model_file.VBRLModel.scorer`) are used instead of the stand-in
    described in the module docstring.
    """
    from vbrl_ros.config import VBRLConfig, VoxelGridConfig
    from vbrl_ros.features.featurizer import Featurizer
    from vbrl_ros.model.builtin import load_paper_model

    if model is not None:
        require_polar(model)
        raw, poses = _rotated_descriptors(model.featurizer(), scans, seed)
        scorer = model.scorer(prune)
        x = model.standardize(np.asarray(raw, np.float64))
        return DescriptorSet("polar", scorer.compact(x).astype(np.float32), scorer,
                             np.array([s for _, _, s in scans]), poses)
    model = load_paper_model()
    grid = model.config.grid
    polar = VoxelGridConfig(kind="polar", sectors=sectors, z_edges=grid.z_edges,
                            max_range=grid.extent_xy)
    featurizer = Featurizer(VBRLConfig(grid=polar, features=model.config.features))
    layout = featurizer.layout
    raw, poses = _rotated_descriptors(featurizer, scans, seed)
    x = np.asarray(raw, np.float64)
    # standardise per column, statistics pooled over scans and sectors (tied)
    columns = x[:, layout.sector_rows]  # (n, S, R)
    mean = columns.mean(axis=(0, 1))
    scale = np.maximum(columns.std(axis=(0, 1)), 1e-3)
    x[:, layout.sector_rows] = (columns - mean) / scale
    w_voxel = _ring_importances(model.w_voxel, grid, polar.rings)
    w_voxel[np.argsort(w_voxel)[: int(round(off_fraction * len(w_voxel)))]] = 0.0
    weights = row_weights(model.w_modality, w_voxel / w_voxel.sum(), layout.weight_layout)
    scorer = WeightedL1Scorer(weights, sector_rows=layout.sector_rows)
    return DescriptorSet("polar", scorer.compact(x).astype(np.float32), scorer,
                         np.array([s for _, _, s in scans]), poses)


def require_polar(model: Any, name: str = "the polar benchmark") -> None:
    """``ValueError`` unless ``model`` was trained on a polar grid (``vbrl train --grid polar``)."""
    if model.config.grid.kind != "polar":
        raise ValueError(f"{name} needs a polar model (vbrl train --grid polar), "
                         f"this one is {model.config.grid.kind}")


def _rotated_descriptors(featurizer: Any, scans: list[tuple[np.ndarray, np.ndarray, int]],
                         seed: int) -> tuple[list[np.ndarray], np.ndarray]:
    """Raw descriptors with every winter scan turned by a seeded random yaw, and their poses."""
    rng = np.random.default_rng([seed, 0x9071])
    raw, poses = [], []
    for points, pose, session in scans:
        yaw = rng.uniform(-math.pi, math.pi) if session == 1 else 0.0
        rotation = _rz(yaw)
        raw.append(featurizer.describe(points @ rotation[:3, :3].T.astype(np.float32)))
        poses.append(pose @ np.linalg.inv(rotation))  # the rotated scan's T_world_lidar
    return raw, np.array(poses)


def _ring_importances(w_voxel: np.ndarray, grid: Any, rings: int) -> np.ndarray:
    """The Cartesian model's voxel importances averaged over each (layer, ring) annulus.

    Ids are ``layer * rings + ring`` (the polar grid's tied voxels). Learned
    importances carry which heights and distances survive seasons; their
    dependence on direction (along or across the street) cannot be tied
    across sectors and averages out.
    """
    cells, extent = grid.cells_xy, grid.extent_xy
    xy = np.linspace(-extent, extent, 401)[:-1] + extent / 400
    xx, yy = np.meshgrid(xy, xy)
    radius = np.hypot(xx, yy).ravel()
    inside = radius < extent
    cell = (((yy.ravel() + extent) // (2 * extent / cells)) * cells
            + (xx.ravel() + extent) // (2 * extent / cells)).astype(np.int64)[inside]
    ring = np.minimum((radius[inside] / (extent / rings)).astype(np.int64), rings - 1)
    layers = len(w_voxel) // cells**2
    out = np.empty(layers * rings)
    for layer in range(layers):
        per_sample = w_voxel[layer * cells**2 + cell]
        out[layer * rings : (layer + 1) * rings] = (
            np.bincount(ring, per_sample, rings) / np.bincount(ring, minlength=rings))
    return out


def relative_yaw(poses: np.ndarray, query: int, match: int) -> float:
    """Yaw of T_query_match = inv(T_world_query) T_world_match (radians, (-pi, pi])."""
    relative = np.linalg.solve(poses[query], poses[match])
    return math.atan2(relative[1, 0], relative[0, 0])


def replicate(base: np.ndarray, n: int, seed: int = 0, mix: float = 0.3, noise: float = 0.2,
              chunk: int = 4096) -> Iterator[np.ndarray]:
    """(<= chunk, d) blocks of n distinct keyframes made of real ones, at memory speed.

    Keyframe i (i >= B) is base[i % B] (the drive, lap after lap) with a
    contiguous ``mix`` fraction of its rows (a few whole sectors of a polar
    descriptor) taken from another real descriptor at the same rows, plus a
    little noise read from a shared random stream at a random offset. Values
    keep the real, heavy-tailed distribution. The first B keyframes are
    ``base``. Blocks reuse one buffer: copy (e.g. ``KeyframeIndex.add_batch``)
    before asking for the next.
    """
    base = np.ascontiguousarray(base, np.float32)
    b, d = base.shape
    rng = np.random.default_rng([seed, 0xB4])
    stream = (noise * rng.standard_normal(2 * d)).astype(np.float32)
    buffer = np.empty((min(chunk, n), d), np.float32)
    for first in range(0, n, chunk):
        i = np.arange(first, min(first + chunk, n))
        partner = (i + 1 + rng.integers(0, max(b - 1, 1), len(i))) % b  # another scan
        out = buffer[: len(i)]
        _replicate(base, i, partner, rng.integers(0, d, len(i)), int(mix * d), stream,
                   rng.integers(0, d, len(i)), out)
        yield out


@njit(cache=True, nogil=True)
def _replicate(base: np.ndarray, index: np.ndarray, partner: np.ndarray, start: np.ndarray,
               width: int, stream: np.ndarray, offset: np.ndarray, out: np.ndarray) -> None:
    b, d = base.shape
    for n in range(len(out)):
        i, row = index[n], out[n]
        if i < b:
            row[:] = base[i]
            continue
        own, other, noise = base[i % b], base[partner[n]], stream[offset[n] : offset[n] + d]
        for j in range(d):
            row[j] = own[j] + noise[j]
        first = start[n]
        stop = min(first + width, d)
        for j in range(first, stop):
            row[j] = other[j] + noise[j]
        for j in range(first + width - stop):  # the part past the end continues at row 0
            row[j] = other[j] + noise[j]


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.eye(4)
    rotation[:2, :2] = [[c, -s], [s, c]]
    return rotation
