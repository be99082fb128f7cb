r"""LPV-DS: a Gaussian-mixture blend of linear systems with one shared Lyapunov function.

Figueroa & Billard, "A Physically-Consistent Bayesian Non-Parametric Mixture Model for
Dynamical System Learning", CoRL 2018. In model coordinates (target at 0),

.. math:: \dot x = \sum_k \gamma_k(x) A_k x, \qquad V(x) = x^\top P x,

with :math:`\gamma_k` the posterior responsibilities of a Gaussian mixture over positions.
The fit has the paper's three steps:

1. **Mixture** (``features``). By default (``"physically_consistent"``) an approximation of
   the paper's physically-consistent GMM: the samples are clustered on the paper's
   similarity, which mixes closeness and the direction of motion,

   .. math:: s_{ij} = \tfrac12 \Big(1 + \frac{\dot x_i^\top \dot x_j}{\|\dot x_i\|
       \|\dot x_j\|}\Big) \exp\Big(-\frac{\|x_i - x_j\|^2}{2 \ell^2}\Big),

   by spectral clustering (one embedding, k-means for every K) instead of the paper's
   collapsed Gibbs sampler of a distance-dependent CRP; each cluster gives a Gaussian over
   positions (its sample mean and covariance), and K is the one of lowest BIC over
   2..K_max, standing in for the non-parametric prior's choice. ``"position_velocity"`` (a
   scikit-learn EM mixture over :math:`(x, \dot x)`, marginalised to positions) and
   ``"position"`` (EM over positions) are the plain alternatives, K by BIC over 1..K_max.
2. **Lyapunov matrix P**, estimated from the data before the linear systems (the paper's
   "P-QLF" variant, with the estimator of Khansari-Zadeh & Billard 2014 that its code uses):

   .. math:: \min_P \frac1N \sum_i J(\psi_i), \quad \psi_i = \frac{(P x_i)^\top \dot x_i}
       {\|P x_i\| \|\dot x_i\|}, \quad J(\psi) = \begin{cases} \psi^2 & \psi > 0 \\
       -w \psi^2 & \psi \le 0 \end{cases}

   (w = 1e-4), the squared cosine of every sample that climbs V, less a small reward for
   descending ones. :math:`\psi` does not depend on P's scale, which is fixed by
   :math:`P = p_{\min} I + n (1 - p_{\min}) M / \operatorname{tr} M`, :math:`M = L L^\top`
   (so :math:`\operatorname{tr} P = n` and :math:`\lambda_{\min}(P) \ge p_{\min}`: a nearly
   singular P would make V flat in one direction). The problem is not convex: L-BFGS from
   P = I and from seeded random starts, keeping the best.
3. **Linear systems** by a convex least-squares program with linear matrix inequalities:

   .. math:: \min_{A_1..A_K} \frac1N \sum_i \Big\|\dot x_i - \sum_k \gamma_k(x_i) A_k x_i
       \Big\|^2 + \beta \sum_k \|A_k\|_F^2 \quad \text{s.t.} \quad
       A_k^\top P + P A_k \preceq -\epsilon I \ \ \forall k.

   The residual is linear in the :math:`A_k`, so a QR factorisation of its design matrix
   reduces the N samples to a (Kn x Kn) system: the program's size does not grow with N.

Solved with cvxpy and Clarabel (or SCS). :math:`\epsilon` is a margin in model units (per
unit of model time, in which a demonstration lasts a few units); the authors' code uses
0.001 per second with trace P = 1 (0.0014-0.004 here on LASA). A larger margin keeps far
random starts converging within the stability check's horizon. The defaults were chosen by
measurement (docs/design.md, "The baselines' defaults"; benchmarks/README.md,
"Baselines: how faithful they are").

**Guarantee:** after solving, the stored :math:`A_k` and P are checked in float64
(:func:`~snds.baselines.mixture.stability_margin`): :math:`P \succ 0` and
:math:`c = \min_k -\lambda_{\max}(A_k^\top P + P A_k) > 0`, so :math:`\dot V \le -c \|x\|^2`
everywhere and the target is globally exponentially stable (for the continuous flow). If
the check fails (a solver's tolerance), the fit tightens :math:`\epsilon` and re-solves,
then falls back to P = I; if nothing verifies, it refuses.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from scipy.optimize import minimize
from torch import Tensor

from snds.baselines.mixture import (
    MixtureConfig,
    MixtureFit,
    MixtureLinearPolicy,
    design_matrix,
    fit_mixture,
    matrices_from_coefficients,
    require,
    single_threaded,
    subsample,
)
from snds.data.demonstrations import Demonstrations, Normalization, Split
from snds.errors import SNDSError
from snds.fitting import Fitted
from snds.losses import make_samples
from snds.spaces import Euclidean, Space

__all__ = [
    "FEATURES",
    "LPVDS",
    "LPVDSPolicy",
    "fit_linear_systems",
    "fit_lyapunov_matrix",
    "lyapunov_matrix_from_factor",
    "lyapunov_violation",
    "physically_consistent_mixture",
    "position_bic",
    "similarity",
]


class LPVDSPolicy(MixtureLinearPolicy):
    r"""LPV-DS: :math:`\dot x = \sum_k \gamma_k(x) A_k x` with a shared :math:`V = x^\top P x`.

    Globally asymptotically stable when fitted by :class:`LPVDS`: the fit stores only
    numbers with :math:`P \succ 0` and :math:`A_k^\top P + P A_k \prec 0` verified in float64,
    and :meth:`decay` returns the verified rate, :math:`\dot V \le -c \|x\|^2`.

    Built as :class:`~snds.baselines.mixture.MixtureLinearPolicy` is.
    """

    kind = "lpvds"


def _solve(problem: Any, solver: str) -> str:
    """Solves a cvxpy problem; returns its status ("solver_error" if the solver raised)."""
    import cvxpy as cp

    try:
        problem.solve(solver=solver)
    except cp.error.SolverError:
        return "solver_error"
    return str(problem.status)


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


def lyapunov_matrix_from_factor(factor: Tensor, min_eigenvalue: float) -> Tensor:
    r""":math:`P = p_{\min} I + n (1 - p_{\min}) M / \operatorname{tr} M` with
    :math:`M = L L^\top`: trace n, every eigenvalue in :math:`[p_{\min}, n]`.

    Arguments:
        factor: L, shape (n, n) (any square matrix; only :math:`L L^\top` matters).
        min_eigenvalue: :math:`p_{\min} \in (0, 1)`.
    """
    n = factor.shape[-1]
    m = factor @ factor.T
    eye = torch.eye(n, dtype=factor.dtype)
    return min_eigenvalue * eye + n * (1.0 - min_eigenvalue) * m / torch.trace(m)


def lyapunov_violation(p: Tensor, x: Tensor, velocities: Tensor, weight: float) -> Tensor:
    r"""The P-QLF objective :math:`\frac1N \sum_i J(\psi_i)` (step 2 of the module docstring).

    Arguments:
        p: P, shape (n, n), symmetric positive definite.
        x: Positions in model coordinates, none at the target, shape (N, n).
        velocities: Their velocities, none zero, shape (N, n).
        weight: w >= 0, the reward for descending samples.
    """
    px = x @ p
    psi = (px * velocities).sum(-1) / (px.norm(dim=-1) * velocities.norm(dim=-1))
    return torch.where(psi > 0, psi**2, -weight * psi**2).mean()


def fit_lyapunov_matrix(
    x: np.ndarray,
    velocities: np.ndarray,
    *,
    min_eigenvalue: float,
    weight: float,
    starts: int,
    seed: int,
) -> tuple[np.ndarray | None, dict]:
    r"""The data-driven estimate of P (step 2 of the module docstring).

    Arguments:
        x: Positions in model coordinates, shape (N, n).
        velocities: Their velocities, shape (N, n).
        min_eigenvalue: :math:`p_{\min}`, below 1 (the trace is n).
        weight: w of the objective.
        starts: L-BFGS runs: from P = I, then from seeded random factors.
        seed: Seed of the random starts.

    Returns:
        P, shape (n, n) (None if no run ended finite), and a record (the objective and the
        fraction of samples that climb V, with P = I and with P; the runs).
    """
    n = x.shape[1]
    # The target itself and standstills carry no direction.
    keep = (np.linalg.norm(x, axis=1) > 1e-12) & (np.linalg.norm(velocities, axis=1) > 1e-12)
    xs = torch.as_tensor(x[keep], dtype=torch.float64)
    vs = torch.as_tensor(velocities[keep], dtype=torch.float64)
    rows, cols = np.tril_indices(n)
    index = (torch.as_tensor(rows), torch.as_tensor(cols))

    def factor(theta: Tensor) -> Tensor:
        return torch.zeros(n, n, dtype=torch.float64).index_put(index, theta)

    def objective(theta: np.ndarray) -> tuple[float, np.ndarray]:
        t = torch.as_tensor(theta, dtype=torch.float64).requires_grad_(True)
        p = lyapunov_matrix_from_factor(factor(t), min_eigenvalue)
        loss = lyapunov_violation(p, xs, vs, weight)
        (grad,) = torch.autograd.grad(loss, t)
        return float(loss.detach()), grad.numpy()

    def climbing(p: np.ndarray) -> float:
        return float((((x[keep] @ p) * velocities[keep]).sum(-1) > 0).mean())

    identity = np.eye(n)[rows, cols]
    rng = np.random.default_rng(seed)
    initial = [identity] + [rng.normal(size=len(rows)) for _ in range(max(starts, 1) - 1)]
    with torch.no_grad():
        at_identity = float(lyapunov_violation(torch.eye(n, dtype=torch.float64), xs, vs, weight))
    record: dict = {"objective_identity": at_identity, "climbing_identity": climbing(np.eye(n))}
    best, runs = None, []
    for theta in initial:
        result = minimize(
            objective, theta, jac=True, method="L-BFGS-B", options={"ftol": 1e-12, "gtol": 1e-10}
        )
        runs.append({"objective": float(result.fun), "iterations": int(result.nit)})
        if np.isfinite(result.fun) and (best is None or result.fun < best.fun):
            best = result
    record["runs"] = runs
    if best is None:
        return None, record
    with torch.no_grad():
        p = lyapunov_matrix_from_factor(factor(torch.as_tensor(best.x)), min_eigenvalue)
        p = p.numpy()
    p = 0.5 * (p + p.T)
    record |= {"objective": float(best.fun), "climbing": climbing(p)}
    return p, record


def fit_linear_systems(
    x: np.ndarray,
    velocities: np.ndarray,
    gamma: np.ndarray,
    lyapunov_matrix: np.ndarray,
    *,
    eps: float,
    ridge: float,
    solver: str,
) -> tuple[np.ndarray | None, dict]:
    r"""The LMI-constrained least squares for the :math:`A_k` (step 3 of the module docstring).

    Arguments:
        x: Positions in model coordinates, shape (N, n).
        velocities: Their velocities, shape (N, n).
        gamma: Responsibilities at the positions, shape (N, K).
        lyapunov_matrix: P, shape (n, n).
        eps: :math:`\epsilon > 0` of the LMIs.
        ridge: :math:`\beta \ge 0`, keeps components with little data bounded.
        solver: A cvxpy solver name.

    Returns:
        The :math:`A_k`, shape (K, n, n) (None if the solver failed), and a record (status,
        the velocity MSE on these samples).
    """
    import cvxpy as cp

    count, n = x.shape
    k = gamma.shape[1]
    design = design_matrix(x, gamma)
    q, r = np.linalg.qr(design)
    projected = q.T @ velocities
    # |design theta - v|^2 = |r theta - q^T v|^2 + (|v|^2 - |q^T v|^2): the remainder is the
    # part of v no theta can reach.
    remainder = float((velocities**2).sum() - (projected**2).sum())
    theta = cp.Variable((k * n, n))
    blocks = [theta[i * n : (i + 1) * n, :].T for i in range(k)]
    objective = cp.sum_squares(r @ theta - projected) / count + ridge * cp.sum_squares(theta)
    constraints = [
        lyapunov_matrix @ a + (lyapunov_matrix @ a).T << -eps * np.eye(n) for a in blocks
    ]
    problem = cp.Problem(cp.Minimize(objective), constraints)
    status = _solve(problem, solver)
    record: dict = {"status": status, "eps": eps}
    if status not in ("optimal", "optimal_inaccurate") or theta.value is None:
        return None, record
    value = theta.value
    record["mse"] = float(((r @ value - projected) ** 2).sum() + remainder) / count
    return matrices_from_coefficients(value), record


#: The mixtures of step 1 (:attr:`LPVDS.features`).
FEATURES = ("physically_consistent", "position_velocity", "position")


@dataclass(frozen=True)
class LPVDS:
    """LPV-DS fitted by a physically-consistent mixture, a data-driven P and an
    LMI-constrained least squares (the three steps of the module docstring).

    Attributes:
        name: "lpvds".
        description: One line for tables.
        has_lyapunov: True: V = x^T P x.
        components: A fixed K, or None to choose it by BIC over ..``max_components``.
        max_components: K_max of the BIC search.
        eps: epsilon of the LMIs A_k^T P + P A_k <= -eps I, in model units (1 / model time).
        min_eigenvalue: p_min of P (with trace P = n).
        lyapunov_weight: w of the P objective (the reward for samples that descend V).
        lyapunov_starts: L-BFGS runs of the P estimate (the first from P = I).
        estimate_lyapunov: False: P = I (the paper's "QLF" variant, SEDS's V).
        ridge: beta, the pull of the A_k towards 0.
        reg_covar: Floor added to the mixture's covariances (squared model units).
        features: How the mixture is found: "physically_consistent" (clusters of the
            paper's position-and-direction similarity), "position_velocity" (EM over
            (x, xdot)) or "position" (EM over x); gamma_k always uses the Gaussians over x.
        length_scale: l of the physically-consistent similarity, model units (extent 1).
        max_samples: Training samples used for the mixture and the P estimate (0: all);
            the A_k program uses all (its size does not depend on N).
        solver: cvxpy solver ("CLARABEL" or "SCS"); the other one is tried if it fails.
    """

    name: str = "lpvds"
    description: str = "LPV-DS: Gaussian-mixture blend of linear systems, shared V = x'Px (LMIs)"
    has_lyapunov: ClassVar[bool] = True
    spaces: ClassVar[tuple[type[Space], ...]] = (Euclidean,)
    components: int | None = None
    max_components: int = 20
    eps: float = 0.05
    min_eigenvalue: float = 0.1
    lyapunov_weight: float = 1e-4
    lyapunov_starts: int = 4
    estimate_lyapunov: bool = True
    ridge: float = 1e-6
    reg_covar: float = 1e-4
    features: str = "physically_consistent"
    length_scale: float = 0.1
    max_samples: int = 2000
    solver: str = "CLARABEL"

    def __post_init__(self) -> None:
        if self.features not in FEATURES:
            raise ValueError(f"features must be one of {FEATURES}, not {self.features!r}")

    def fit(
        self,
        demos: Demonstrations,
        split: Split,
        *,
        seed: int = 0,
        steps: int | None = None,
        progress: bool = False,
    ) -> Fitted:
        """Fits an :class:`LPVDSPolicy`; ``steps`` and ``progress`` are ignored (convex fit).

        Raises:
            SNDSError: If no fitted system passes the stability verification.
        """
        with single_threaded():
            return self._fit(demos, split, seed=seed)

    def _fit(self, demos: Demonstrations, split: Split, *, seed: int) -> Fitted:
        """The fit itself (see :meth:`fit`), with one BLAS / OpenMP thread."""
        normalization = Normalization.fit(demos)
        samples = make_samples(demos, normalization, split, window=0)
        x = samples.positions.numpy()
        v = samples.velocities.numpy()
        rng = np.random.default_rng(seed)
        # Import the extra's modules before the clock (a second, like torch's for SNDS), and
        # fail now, with the install hint, if they are missing.
        require("cvxpy")
        require("sklearn.mixture")
        start = time.perf_counter()
        few = subsample(len(x), self.max_samples, rng)
        if self.features == "physically_consistent":
            mixture = physically_consistent_mixture(
                x[few],
                v[few],
                components=self.components,
                max_components=self.max_components,
                length_scale=self.length_scale,
                reg_covar=self.reg_covar,
                seed=seed,
            )
        else:
            points = x[few] if self.features == "position" else np.concatenate([x, v], 1)[few]
            mixture = fit_mixture(
                points,
                components=self.components,
                max_components=self.max_components,
                seed=seed,
                reg_covar=self.reg_covar,
            ).marginal(demos.dim)
        policy = LPVDSPolicy(
            dim=demos.dim,
            normalization=normalization,
            config=MixtureConfig(components=mixture.components),
        )
        fallbacks: list[str] = []
        solvers = [self.solver] + [s for s in ("CLARABEL", "SCS") if s != self.solver]
        p, p_record = self._lyapunov_matrix(x[few], v[few], seed, fallbacks)
        p, margin, a_record = self._linear_systems(policy, mixture, x, v, p, solvers, fallbacks)
        seconds = time.perf_counter() - start
        record = {
            "lpvds": {
                "settings": {
                    k: val for k, val in asdict(self).items() if k not in ("name", "description")
                },
                "components": mixture.components,
                "bic": {str(k): val for k, val in mixture.bic.items()},
                "samples": len(x),
                "samples_mixture": len(few),
                "lyapunov_program": p_record,
                "lyapunov_matrix": p.tolist(),
                "lyapunov_eigenvalues": np.linalg.eigvalsh(p).tolist(),
                "systems_program": a_record,
                "margin": margin,
                "fallbacks": fallbacks,
                "seed": seed,
            }
        }
        return Fitted(policy=policy, seconds=seconds, record=record)

    def _lyapunov_matrix(
        self, x: np.ndarray, v: np.ndarray, seed: int, fallbacks: list[str]
    ) -> tuple[np.ndarray, dict]:
        """P from :func:`fit_lyapunov_matrix`, or I if not estimated or if the estimate failed.

        Arguments:
            x: Positions (N, n) in model coordinates.
            v: Their velocities (N, n).
            seed: Seed of the estimate's random starts.
            fallbacks: Appended with what failed.

        Returns:
            P, shape (n, n), and the estimate's record.
        """
        if not self.estimate_lyapunov:
            return np.eye(x.shape[1]), {"status": "P = I (not estimated)"}
        p, record = fit_lyapunov_matrix(
            x,
            v,
            min_eigenvalue=self.min_eigenvalue,
            weight=self.lyapunov_weight,
            starts=self.lyapunov_starts,
            seed=seed,
        )
        if p is not None:
            return p, record
        fallbacks.append("P estimate not finite")
        fallbacks.append("P = I")
        return np.eye(x.shape[1]), record

    def _linear_systems(
        self,
        policy: LPVDSPolicy,
        mixture: MixtureFit,
        x: np.ndarray,
        v: np.ndarray,
        p: np.ndarray,
        solvers: list[str],
        fallbacks: list[str],
    ) -> tuple[np.ndarray, float, dict]:
        """Solves for the A_k until the stored numbers pass the check; stores them in ``policy``.

        A solver's answer may miss the LMIs by its tolerance: then eps is tightened (x10,
        twice), then P = I is tried (always feasible: A_k = -I), and if nothing verifies the
        fit is refused rather than an unverified policy returned.

        Arguments:
            policy: The policy to fill.
            mixture: The mixture over positions.
            x: Positions (N, n) in model coordinates.
            v: Their velocities (N, n).
            p: The Lyapunov matrix from :meth:`_lyapunov_matrix`.
            solvers: cvxpy solvers to try in order.
            fallbacks: Appended with what failed.

        Returns:
            The P used, the verified margin and the last program's record.

        Raises:
            SNDSError: If no attempt passes the check.
        """
        gamma = mixture.responsibilities(x)
        identity = np.eye(x.shape[1])
        attempts = [(p, self.eps * 10**i, solver) for i in range(3) for solver in solvers]
        attempts += [(identity, self.eps, solver) for solver in solvers]
        for lyapunov_matrix, eps, solver in attempts:
            matrices, record = fit_linear_systems(
                x, v, gamma, lyapunov_matrix, eps=eps, ridge=self.ridge, solver=solver
            )
            record["solver"] = solver
            if matrices is None:
                fallbacks.append(f"A program {record['status']} with {solver} (eps {eps:g})")
                continue
            try:
                margin = policy.set_fitted(
                    weights=mixture.weights,
                    means=mixture.means,
                    covariances=mixture.covariances,
                    matrices=matrices,
                    lyapunov_matrix=lyapunov_matrix,
                )
            except SNDSError as error:
                fallbacks.append(f"eps {eps:g} with {solver}: {error}")
                continue
            return lyapunov_matrix, margin, record
        raise SNDSError(f"LPV-DS: no fit passed the stability check ({'; '.join(fallbacks)})")
