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

Step 1 lives in :mod:`snds.baselines.lpvds_mixture`, steps 2 and 3 in
:mod:`snds.baselines.lpvds_programs` (their functions are importable from here too); this
module holds the policy and :class:`LPVDS`, which runs the steps and verifies the result.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np

from snds.baselines.lpvds_mixture import (
    physically_consistent_mixture,
    position_bic,
    similarity,
)
from snds.baselines.lpvds_programs import (
    fit_linear_systems,
    fit_lyapunov_matrix,
    lyapunov_matrix_from_factor,
    lyapunov_violation,
)
from snds.baselines.mixture import (
    MixtureConfig,
    MixtureFit,
    MixtureLinearPolicy,
    fit_mixture,
    require,
    single_threaded,
    subsample,
)
from snds.data.demonstrations import Demonstrations, Normalization, Split
from snds.errors import SNDSError
from snds.fitting import Fitted, refuse_other_spaces
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
        refuse_other_spaces(self.name, self.spaces, demos)
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
