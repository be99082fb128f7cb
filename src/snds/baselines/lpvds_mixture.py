r"""Step 1 of LPV-DS (:mod:`snds.baselines.lpvds`): the physically-consistent mixture.

The samples are clustered on the paper's similarity of positions and directions of motion
(:func:`similarity`) by spectral clustering, each cluster gives a Gaussian over positions,
and K is the one of lowest BIC (:func:`position_bic`): :func:`physically_consistent_mixture`.
"""

from __future__ import annotations

import math

import numpy as np

from snds.baselines.mixture import MixtureFit, require
from snds.errors import SNDSError

__all__ = ["physically_consistent_mixture", "position_bic", "similarity"]


def similarity(x: np.ndarray, velocities: np.ndarray, length_scale: float) -> np.ndarray:
    r"""The paper's physically-consistent similarity :math:`s_{ij}` of samples, shape (N, N).

    :math:`s_{ij} = \frac12 (1 + \cos \angle(\dot x_i, \dot x_j))
    \exp(-\|x_i - x_j\|^2 / 2\ell^2)`, in [0, 1], 1 on the diagonal of moving samples; a
    sample at rest counts as every direction's half-match.

    Arguments:
        x: Positions, shape (N, n).
        velocities: Their velocities, shape (N, n).
        length_scale: :math:`\ell`, in the units of x.
    """
    speed = np.linalg.norm(velocities, axis=1, keepdims=True)
    directions = np.divide(velocities, speed, out=np.zeros_like(velocities), where=speed > 0)
    squared = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    return 0.5 * (1.0 + directions @ directions.T) * np.exp(-squared / (2.0 * length_scale**2))


def position_bic(x: np.ndarray, mixture: MixtureFit) -> float:
    r""":math:`-2 \log L + p \log N` of a full-covariance mixture over positions (N, n)."""
    k, n = mixture.means.shape
    log_density = np.stack(
        [
            np.log(w)
            - 0.5 * np.linalg.slogdet(2 * np.pi * c)[1]
            - 0.5 * np.einsum("ij,jk,ik->i", x - m, np.linalg.inv(c), x - m)
            for w, m, c in zip(mixture.weights, mixture.means, mixture.covariances)
        ]
    )
    peak = log_density.max(0)
    log_likelihood = float((peak + np.log(np.exp(log_density - peak).sum(0))).sum())
    parameters = k * (n + n * (n + 1) // 2) + k - 1
    return -2.0 * log_likelihood + parameters * math.log(len(x))


def physically_consistent_mixture(
    x: np.ndarray,
    velocities: np.ndarray,
    *,
    components: int | None,
    max_components: int,
    length_scale: float,
    reg_covar: float,
    seed: int,
) -> MixtureFit:
    r"""Clusters samples on :func:`similarity` and fits a Gaussian over positions per cluster.

    Spectral clustering (Ng, Jordan & Weiss): the leading eigenvectors of the normalised
    similarity, once, then seeded k-means on the first K of them, row-normalised, for every
    K tried; each cluster's Gaussian is its positions' mean and covariance (plus
    ``reg_covar`` on the diagonal), weighted by its share of samples; K is ``components``
    or the lowest :func:`position_bic` over 2..``max_components``.

    Arguments:
        x: Positions in model coordinates, shape (N, n).
        velocities: Their velocities, shape (N, n).
        components: A fixed K, or None to choose by BIC.
        max_components: The largest K tried.
        length_scale: :math:`\ell` of the similarity, model units.
        reg_covar: Added to every covariance's diagonal (squared model units).
        seed: Seed of the embedding's solver and of k-means.
    """
    spectral_embedding = require("sklearn.manifold").spectral_embedding
    k_means = require("sklearn.cluster").KMeans
    n = x.shape[1]
    largest = min(components or max_components, len(x) // (n + 1))
    if largest < 1:
        raise SNDSError(f"cannot fit a mixture to {len(x)} points")
    embedding = spectral_embedding(
        similarity(x, velocities, length_scale),
        n_components=largest,
        drop_first=False,
        random_state=seed,
    )
    candidates = [largest] if components is not None else range(min(2, largest), largest + 1)
    best, best_bic, bic = None, math.inf, {}
    for k in candidates:
        rows = (
            embedding[:, :k] / np.maximum(np.linalg.norm(embedding[:, :k], axis=1), 1e-12)[:, None]
        )
        labels = k_means(n_clusters=k, n_init=4, random_state=seed).fit_predict(rows)
        # A cluster of fewer than n + 1 points has no covariance: it joins no Gaussian.
        members = [labels == j for j in range(k) if (labels == j).sum() > n]
        counts = np.array([m.sum() for m in members], dtype=np.float64)
        mixture = MixtureFit(
            weights=counts / counts.sum(),
            means=np.stack([x[m].mean(0) for m in members]),
            covariances=np.stack(
                [np.atleast_2d(np.cov(x[m].T)) + reg_covar * np.eye(n) for m in members]
            ),
            bic={},
        )
        bic[k] = position_bic(x, mixture)
        if bic[k] < best_bic:
            best, best_bic = mixture, bic[k]
    assert best is not None  # candidates is never empty
    return MixtureFit(best.weights, best.means, best.covariances, bic)
