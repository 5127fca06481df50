"""Surface normal and planarity of small neighbourhoods of points, in closed form.

The agreement of a registration weighs each matched point's surface normal by how planar its
neighbourhood is (:mod:`~vbrl_ros.detection.overlap`). numpy's batched ``eigh`` on thousands of
3 x 3 covariances was the largest part of that test; a symmetric 3 x 3 matrix has closed-form
eigenvalues (the trigonometric solution of its characteristic cubic), and the eigenvector of
the smallest is the largest cross product of two rows of ``A - l_min I``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def surfaces(points: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normals (n, 3) unit, planarity (n,)) of the neighbourhoods ``points[neighbours[i]]``
    ((n, k) indices): the smallest principal axis of each, and (l2 - l1) / l3 of its spread
    (l1 <= l2 <= l3; 1 on a plane, 0 for a line or scattered clutter)."""
    normals = np.zeros((len(neighbours), 3))
    planarity = np.zeros(len(neighbours))
    _surfaces(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(neighbours, dtype=np.int64),
              normals, planarity)
    return normals, planarity


@njit(cache=True, nogil=True)
def _surfaces(points, neighbours, normals, planarity):  # pragma: no cover - compiled
    k = neighbours.shape[1]
    for n in range(neighbours.shape[0]):
        mx = my = mz = 0.0
        for j in range(k):
            p = neighbours[n, j]
            mx += points[p, 0]
            my += points[p, 1]
            mz += points[p, 2]
        mx /= k
        my /= k
        mz /= k
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
        for j in range(k):
            p = neighbours[n, j]
            x, y, z = points[p, 0] - mx, points[p, 1] - my, points[p, 2] - mz
            a00 += x * x
            a01 += x * y
            a02 += x * z
            a11 += y * y
            a12 += y * z
            a22 += z * z
        off = a01 * a01 + a02 * a02 + a12 * a12
        q = (a00 + a11 + a22) / 3.0
        p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * off
        if p2 <= 1e-30 * max(q * q, 1e-300):  # isotropic (or all points equal): no surface
            normals[n, 2] = 1.0
            continue
        p = math.sqrt(p2 / 6.0)
        b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
        b01, b02, b12 = a01 / p, a02 / p, a12 / p
        r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
        r = min(1.0, max(-1.0, r))
        phi = math.acos(r) / 3.0
        largest = q + 2.0 * p * math.cos(phi)
        smallest = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
        middle = 3.0 * q - largest - smallest
        planarity[n] = (middle - smallest) / max(largest, 1e-12)
        # rows of A - smallest I; the normal is orthogonal to all of them
        r0x, r0y, r0z = a00 - smallest, a01, a02
        r1x, r1y, r1z = a01, a11 - smallest, a12
        r2x, r2y, r2z = a02, a12, a22 - smallest
        best = -1.0
        for c in range(3):
            if c == 0:
                ux, uy, uz = r0y * r1z - r0z * r1y, r0z * r1x - r0x * r1z, r0x * r1y - r0y * r1x
            elif c == 1:
                ux, uy, uz = r0y * r2z - r0z * r2y, r0z * r2x - r0x * r2z, r0x * r2y - r0y * r2x
            else:
                ux, uy, uz = r1y * r2z - r1z * r2y, r1z * r2x - r1x * r2z, r1x * r2y - r1y * r2x
            norm = ux * ux + uy * uy + uz * uz
            if norm > best:
                best = norm
                normals[n, 0], normals[n, 1], normals[n, 2] = ux, uy, uz
        length = math.sqrt(best)
        if length > 0.0:
            for c in range(3):
                normals[n, c] /= length
        else:  # a line or a point: no plane (planarity ~0 already weighs it out)
            normals[n, 0], normals[n, 1], normals[n, 2] = 0.0, 0.0, 1.0
