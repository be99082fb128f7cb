r"""Steps 2 and 3 of LPV-DS (:mod:`snds.baselines.lpvds`): the two programs of its fit.

:func:`fit_lyapunov_matrix` estimates the Lyapunov matrix P from the data (the P-QLF
objective :func:`lyapunov_violation` over :func:`lyapunov_matrix_from_factor`, by L-BFGS);
:func:`fit_linear_systems` then solves the LMI-constrained least squares for the linear
systems :math:`A_k` (cvxpy, imported when a fit runs).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from scipy.optimize import minimize
from torch import Tensor

from snds.baselines.mixture import design_matrix, matrices_from_coefficients

__all__ = [
    "fit_linear_systems",
    "fit_lyapunov_matrix",
    "lyapunov_matrix_from_factor",
    "lyapunov_violation",
]


def _solve(problem: Any, solver: str) -> str:
    """Solves a cvxpy problem; returns its status ("solver_error" if the solver raised)."""
    import cvxpy as cp

    try:
        problem.solve(solver=solver)
    except cp.error.SolverError:
        return "solver_error"
    return str(problem.status)


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
    r"""The P-QLF objective :math:`\frac1N \sum_i J(\psi_i)` (step 2 of
    :mod:`snds.baselines.lpvds`).

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
    r"""The data-driven estimate of P (step 2 of :mod:`snds.baselines.lpvds`).

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
    r"""The LMI-constrained least squares for the :math:`A_k` (step 3 of
    :mod:`snds.baselines.lpvds`).

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
