"""Closed-form normals and planarity against numpy's eigen-decomposition, and the degenerate cases."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from vbrl_ros.detection.surface_normals import surfaces


def test_agrees_with_eigh_on_a_scanned_scene():
    rng = np.random.default_rng(0)
    # walls, ground, poles and clutter at 0.5 m spacing: planes, lines and blobs
    wall = np.c_[rng.uniform(-10, 10, 800), np.full(800, 4.0), rng.uniform(0, 3, 800)]
    ground = np.c_[rng.uniform(-10, 10, (1500, 2)), np.zeros(1500)]
    pole = np.c_[np.zeros(60), np.zeros(60), np.linspace(0, 5, 60)]
    clutter = rng.normal([5.0, -3.0, 1.0], 0.6, (300, 3))
    points = np.vstack([wall, ground, pole, clutter]) + rng.normal(0, 0.01, (2660, 3))
    _, neighbours = cKDTree(points).query(points, k=8)
    normals, planarity = surfaces(points, neighbours)
    local = points[neighbours] - points[neighbours].mean(axis=1, keepdims=True)
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    expected = (values[:, 1] - values[:, 0]) / np.maximum(values[:, 2], 1e-12)
    np.testing.assert_allclose(planarity, expected, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    planar = expected > 0.1  # where the normal means something (the sign does not)
    assert np.abs(np.einsum("ni,ni->n", normals, vectors[:, :, 0]))[planar].min() > 1 - 1e-9
    # the wall's normal is y, the ground's z
    assert np.median(np.abs(normals[:800, 1])) > 0.99 and np.median(np.abs(normals[800:2300, 2])) > 0.99


def test_lines_and_repeated_points_have_no_plane():
    line = np.c_[np.arange(8.0), np.zeros(8), np.zeros(8)]
    same = np.ones((8, 3))
    for points in (line, same):
        normals, planarity = surfaces(points, np.arange(8)[None])
        assert abs(planarity[0]) < 1e-9 and np.isclose(np.linalg.norm(normals[0]), 1.0)
