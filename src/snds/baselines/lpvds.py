r"""LPV-DS: a Gaussian-mixture blend of linear systems with one shared Lyapunov function.

Figueroa & Billard, "A Physically-Consistent Bayesian Non-Parametric Mixture Model for
Dynamical System Learning", CoRL 2018. In model coordinates (target at 0),

.. math:: \dot x = \sum_k \gamma_k(x) A_k x, \qquad V(x) = x^\top P x,

with :math:`\gamma_k` the posterior responsibilities of a Gaussian mixture over positions.
The fit has three steps, written here from the paper's maths:

1. **Mixture.** A full-covariance Gaussian mixture (scikit-learn EM, seeded), K chosen by
   BIC over 1..K_max, fitted by default to the training pairs :math:`(x, \dot x)` and
   marginalised to positions (``features="position"`` fits positions alone). The paper uses
   a Bayesian non-parametric, "physically consistent" mixture whose clusters also respect
   the motion's direction; the joint mixture is a plain stand-in with the same aim, and it
   fits better than the mixture over positions (docs/design.md, "The baselines' defaults").
2. **Lyapunov matrix P** (convex stand-in for the paper's non-convex estimate):

   .. math:: \min_P \frac1N \sum_i \max\Big(0, \frac{x_i^\top P \dot x_i}
       {\|x_i\| \|\dot x_i\|}\Big) + \lambda \|P - I\|_F^2
       \quad \text{s.t.} \quad P \succeq p_{\min} I, \ \operatorname{tr} P = n.

   The hinge counts, with every sample weighted alike (hence the normalisation), how much
   the demonstrations themselves climb V; a P under which they descend leaves the LMIs below
   free to fit them. The trace fixes the scale (V and its sign pattern are scale-free), the
   floor :math:`p_{\min}` bounds the condition number (a nearly singular P would make V
   almost flat in one direction), and the small :math:`\lambda` picks, among equally good
   P, the least anisotropic one (P = I, SEDS's V, when that already works).
3. **Linear systems** by a convex least-squares program with linear matrix inequalities:

   .. math:: \min_{A_1..A_K} \frac1N \sum_i \Big\|\dot x_i - \sum_k \gamma_k(x_i) A_k x_i
       \Big\|^2 + \beta \sum_k \|A_k\|_F^2 \quad \text{s.t.} \quad
       A_k^\top P + P A_k \preceq -\epsilon I \ \ \forall k.

   The residual is linear in the :math:`A_k`, so a QR factorisation of its design matrix
   reduces the N samples to a (Kn x Kn) system: the program's size does not grow with N.

Solved with cvxpy and Clarabel (or SCS). The default :math:`\epsilon = 0.05` (per unit of
model time, in which a demonstration lasts a few units) was chosen by measurement
(docs/design.md, "The baselines' defaults"): smaller margins let blends far from the data
contract too slowly to arrive in useful time.

**Guarantee:** after solving, the stored :math:`A_k` and P are checked in float64
(:func:`~snds.baselines.mixture.stability_margin`): :math:`P \succ 0` and
:math:`c = \min_k -\lambda_{\max}(A_k^\top P + P A_k) > 0`, so :math:`\dot V \le -c \|x\|^2`
everywhere and the target is globally exponentially stable (for the continuous flow). If
the check fails (a solver's tolerance), the fit tightens :math:`\epsilon` and re-solves,
then falls back to P = I; if nothing verifies, it refuses.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any, ClassVar

import numpy as np

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
from snds.losses import make_samples
from snds.method import Fitted, Method


class LPVDSPolicy(MixtureLinearPolicy):
    r"""LPV-DS: :math:`\dot x = \sum_k \gamma_k(x) A_k x` with a shared :math:`V = x^\top P x`.

    Globally asymptotically stable when fitted by :class:`LPVDS`: the fit stores only
    numbers with :math:`P \succ 0` and :math:`A_k^\top P + P A_k \prec 0` verified in float64,
    and :meth:`decay` returns the verified rate, :math:`\dot V \le -c \|x\|^2`.

    Arguments:
        dim: State dimension n.
        normalization: The task's affine map of space and time.
        config: The number of components.
        seed: Unused (nothing is random before the fit); kept for the common signature.
    """

    kind = "lpvds"
    config_class = MixtureConfig

    def __init__(
        self, *, dim: int, normalization: Normalization, config: MixtureConfig, seed: int = 0
    ) -> None:
        super().__init__(dim=dim, normalization=normalization, components=config.components)
        self.config = config


def _solve(problem: Any, solver: str) -> str:
    """Solves a cvxpy problem; returns its status ("solver_error" if the solver raised)."""
    import cvxpy as cp

    try:
        problem.solve(solver=solver)
    except cp.error.SolverError:
        return "solver_error"
    return str(problem.status)


def fit_lyapunov_matrix(
    x: np.ndarray,
    velocities: np.ndarray,
    *,
    min_eigenvalue: float,
    smoothing: float,
    solver: str,
) -> tuple[np.ndarray | None, dict]:
    r"""The convex estimate of P (step 2 of the module docstring).

    Arguments:
        x: Positions in model coordinates, shape (N, n).
        velocities: Their velocities, shape (N, n).
        min_eigenvalue: :math:`p_{\min}`, below 1 (the trace is n).
        smoothing: :math:`\lambda`, the pull towards I.
        solver: A cvxpy solver name.

    Returns:
        P, shape (n, n) (None if the solver failed), and a record (status, the mean hinge
        before and after, i.e. with P = I and with P).
    """
    import cvxpy as cp

    n = x.shape[1]
    scale = np.linalg.norm(x, axis=1) * np.linalg.norm(velocities, axis=1)
    keep = scale > 1e-12  # the target itself and standstills carry no direction
    # x^T P v = <P, x v^T>: one row of coefficients per sample, linear in P's entries.
    outer = (x[keep, :, None] * velocities[keep, None, :] / scale[keep, None, None]).reshape(
        -1, n * n
    )
    p = cp.Variable((n, n), symmetric=True)
    hinge = cp.sum(cp.pos(outer @ cp.reshape(p, (n * n,), order="C"))) / max(len(outer), 1)
    problem = cp.Problem(
        cp.Minimize(hinge + smoothing * cp.sum_squares(p - np.eye(n))),
        [p >> min_eigenvalue * np.eye(n), cp.trace(p) == n],
    )
    status = _solve(problem, solver)
    identity_hinge = float(np.maximum(outer @ np.eye(n).ravel(), 0).mean()) if len(outer) else 0
    record = {"status": status, "hinge_identity": identity_hinge}
    if status not in ("optimal", "optimal_inaccurate") or p.value is None:
        return None, record
    value = 0.5 * (p.value + p.value.T)
    record["hinge"] = float(np.maximum(outer @ value.ravel(), 0).mean()) if len(outer) else 0
    return value, record


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


@dataclass(frozen=True)
class LPVDS(Method):
    """LPV-DS fitted by a mixture, a convex P estimate and an LMI-constrained least squares.

    Attributes:
        name: "lpvds".
        description: One line for tables.
        has_lyapunov: True: V = x^T P x.
        components: A fixed K, or None to choose it by BIC over 1..``max_components``.
        max_components: K_max of the BIC search.
        eps: epsilon of the LMIs A_k^T P + P A_k <= -eps I, in model units (1 / model time).
        min_eigenvalue: p_min of P (with trace P = n).
        smoothing: lambda, the pull of P towards I.
        ridge: beta, the pull of the A_k towards 0.
        reg_covar: Floor added to the mixture's covariances (squared model units).
        features: What the mixture is fitted to: "position" (x), or "position_velocity"
            (x, xdot), whose clusters also separate differing motion directions (the aim of
            the paper's physically consistent mixture); either way gamma_k uses the mixture
            over x (the marginal).
        max_samples: Training samples used for the mixture and the P program (0: all);
            the A_k program uses all (its size does not depend on N).
        solver: cvxpy solver ("CLARABEL" or "SCS"); the other one is tried if it fails.
    """

    name: str = "lpvds"
    description: str = "LPV-DS: Gaussian-mixture blend of linear systems, shared V = x'Px (LMIs)"
    has_lyapunov: ClassVar[bool] = True
    components: int | None = None
    max_components: int = 20
    eps: float = 0.05
    min_eigenvalue: float = 0.1
    smoothing: float = 1e-3
    ridge: float = 1e-6
    reg_covar: float = 1e-4
    features: str = "position_velocity"
    max_samples: int = 2000
    solver: str = "CLARABEL"

    def __post_init__(self) -> None:
        if self.features not in ("position", "position_velocity"):
            raise ValueError(
                f"features must be 'position' or 'position_velocity', not {self.features!r}"
            )

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
        p, p_record = self._lyapunov_matrix(x[few], v[few], solvers, fallbacks)
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
        self, x: np.ndarray, v: np.ndarray, solvers: list[str], fallbacks: list[str]
    ) -> tuple[np.ndarray, dict]:
        """P from :func:`fit_lyapunov_matrix` with the first solver that succeeds, else I.

        Arguments:
            x: Positions (N, n) in model coordinates.
            v: Their velocities (N, n).
            solvers: cvxpy solvers to try in order.
            fallbacks: Appended with what failed.

        Returns:
            P, shape (n, n), and the program's record.
        """
        record: dict = {}
        for solver in solvers:
            p, record = fit_lyapunov_matrix(
                x, v, min_eigenvalue=self.min_eigenvalue, smoothing=self.smoothing, solver=solver
            )
            record["solver"] = solver
            if p is not None:
                return p, record
            fallbacks.append(f"P program {record['status']} with {solver}")
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
