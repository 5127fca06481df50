"""How well a registered pose is supported: inlier correspondences, their RMSE and the pose's
covariance (conventions: :mod:`vbrl_ros.detection.registration`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vbrl_ros.detection.prepared_cloud import PreparedCloud


@dataclass(frozen=True)
class InlierStatistics:
    inlier: np.ndarray  # (n,) bool per source point: a match point within the threshold
    rmse: float  # metres, over inliers (inf without any)
    covariance: np.ndarray | None  # (6, 6) [translation, rotation]; None when not positive definite


def inlier_statistics(source: np.ndarray, match: PreparedCloud, T_query_match: np.ndarray,
                      threshold: float, min_inliers: int) -> InlierStatistics:
    """Correspondences of the query-frame ``source`` points with ``match`` (searched in the match's
    own frame) within ``threshold``; RMSE and covariance from at least ``min_inliers`` of them."""
    R, t = T_query_match[:3, :3], T_query_match[:3, 3]
    distances, nearest = match.tree.query((source - t) @ R, distance_upper_bound=threshold)
    inlier = np.isfinite(distances)
    n_in = int(inlier.sum())
    if n_in < min_inliers:
        return InlierStatistics(inlier, float("inf"), None)
    q, p = source[inlier], match.points[nearest[inlier]] @ R.T + t
    residuals = q - p
    rmse = float(np.sqrt(np.mean(np.einsum("ij,ij->i", residuals, residuals))))
    # Per-coordinate residual variance, with 6 degrees of freedom used by the fit.
    sigma2 = float(np.sum(residuals**2) / max(3 * n_in - 6, 1))
    return InlierStatistics(inlier, rmse, _covariance(p, sigma2))


def _covariance(p: np.ndarray, sigma2: float) -> np.ndarray | None:
    """sigma^2 (sum J^T J)^-1 with J = [I, -hat(p)] for each aligned match point p."""
    n = len(p)
    # sum J^T J = [[n I, -sum hat(p)], [sum hat(p), -sum hat(p)^2]], in closed form
    s = p.sum(axis=0)
    hat_s = _hat(s)
    second = (p.T @ p)  # sum p p^T
    minus_hat2 = np.trace(second) * np.eye(3) - second  # -sum hat(p)^2
    H = np.block([[n * np.eye(3), -hat_s], [hat_s, minus_hat2]])
    try:
        L = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        return None
    L_inv = np.linalg.inv(L)
    covariance = sigma2 * (L_inv.T @ L_inv)
    covariance = 0.5 * (covariance + covariance.T)
    return covariance if np.all(np.isfinite(covariance)) else None


def _hat(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
