r"""SEDS: Gaussian mixture regression whose every component is a stable linear system.

Khansari-Zadeh & Billard, "Learning Stable Nonlinear Dynamical Systems With Gaussian Mixture
Models", IEEE T-RO 2011. In model coordinates (target at 0), Gaussian mixture regression of
:math:`\dot x` on :math:`x` with every regression line through the target gives

.. math:: \dot x = \sum_k h_k(x) A_k x, \qquad
    h_k(x) = \frac{\pi_k \mathcal N(x; \mu_k, \Sigma_k)}{\sum_j \pi_j \mathcal N(x; \mu_j,
    \Sigma_j)},

and the paper's sufficient conditions for global asymptotic stability with
:math:`V = \|x\|^2` are :math:`A_k + A_k^\top \prec 0` for every k.

The fit (written from the paper's maths; its "MSE" variant) minimises the velocity error
:math:`\frac1N \sum_i \|\dot x_i - \sum_k h_k(x_i) A_k x_i\|^2` over all the parameters,
priors, means and covariances included, with a parametrisation that satisfies the
constraints by construction instead of the paper's constrained SQP:

.. math:: A_k = -(L_k L_k^\top + \epsilon I) + (S_k - S_k^\top), \quad
    \Sigma_k = C_k C_k^\top + r I, \quad \pi = \operatorname{softmax}(w),

with :math:`C_k` lower triangular with a positive (exponentiated) diagonal. The symmetric part
of every :math:`A_k` is :math:`-(L_k L_k^\top + \epsilon I) \preceq -\epsilon I`, so
:math:`A_k + A_k^\top \preceq -2\epsilon I` whatever the optimiser does. It starts from a
scikit-learn mixture over :math:`(x, \dot x)` (K by BIC, as the paper's initialisation) and
the least-squares :math:`A_k` for its responsibilities, projected onto the constraint set,
and runs full-batch L-BFGS in float64 (deterministic given the seed). The defaults
(:math:`\epsilon = 0.02`, K_max = 15) were chosen by measurement (docs/design.md, "The
baselines' defaults").

**Guarantee:** global exponential stability of the target for the continuous flow:
:math:`\dot V \le -c \|x\|^2` with :math:`V = \|x\|^2` and
:math:`c = \min_k -\lambda_{\max}(A_k + A_k^\top) \ge 2\epsilon`, checked in float64 on the
stored numbers before the policy is returned. The price of the shared, isotropic V: a
demonstration that moves away from the target at some point (its distance grows) cannot be
reproduced there. LPV-DS relaxes exactly this with a learned P.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from snds.baselines.mixture import (
    MixtureConfig,
    MixtureLinearPolicy,
    blend,
    design_matrix,
    fit_mixture,
    log_responsibilities,
    matrices_from_coefficients,
    require,
    single_threaded,
    subsample,
)
from snds.data.demonstrations import Demonstrations, Normalization, Split
from snds.fitting import Fitted, refuse_other_spaces
from snds.losses import make_samples
from snds.spaces import Euclidean, Space

__all__ = ["SEDS", "SEDSPolicy"]


class SEDSPolicy(MixtureLinearPolicy):
    r"""SEDS: :math:`\dot x = \sum_k h_k(x) A_k x` with :math:`A_k + A_k^\top \prec 0`.

    Its Lyapunov function is :math:`V = \|x\|^2` (P = I, :attr:`lyapunov` ``.quadratic`` = 1);
    when fitted by :class:`SEDS`, :meth:`decay` returns the verified rate
    :math:`c \ge 2\epsilon` of :math:`\dot V \le -c \|x\|^2`.

    Built as :class:`~snds.baselines.mixture.MixtureLinearPolicy` is.
    """

    kind = "seds"


def _project_stable(matrices: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    r"""Factors :math:`(L_k, S_k)` of the closest admissible :math:`A_k` to given matrices.

    The skew part is kept; the symmetric part :math:`H` is replaced by the nearest matrix
    (in Frobenius norm) with eigenvalues :math:`\le -2\epsilon`, i.e. its eigenvalues are
    clipped, and :math:`L L^\top = -H' - \epsilon I`.

    Arguments:
        matrices: Any :math:`A_k`, shape (K, n, n).
        eps: The :math:`\epsilon` of the parametrisation.

    Returns:
        :math:`L_k` and :math:`S_k`, each shape (K, n, n).
    """
    sym = 0.5 * (matrices + np.swapaxes(matrices, -1, -2))
    skew = 0.5 * (matrices - np.swapaxes(matrices, -1, -2))
    values, vectors = np.linalg.eigh(-sym)
    # Clipping at 2 eps (not eps) keeps L away from singular, where its gradient is small.
    values = np.maximum(values, 2.0 * eps) - eps
    factors = vectors * np.sqrt(values)[..., None, :]
    return factors, 0.5 * skew  # S - S^T = skew for S = skew / 2


class _SEDSParameters(nn.Module):
    r"""The unconstrained parametrisation optimised by :class:`SEDS` (used only in the fit).

    Arguments:
        weights: Initial priors, shape (K,).
        means: Initial means over positions, shape (K, n).
        covariances: Initial covariances over positions, shape (K, n, n).
        matrices: Initial :math:`A_k` (projected onto the constraints), shape (K, n, n).
        eps: :math:`\epsilon` in :math:`A_k`.
        reg_covar: :math:`r` in :math:`\Sigma_k`.
    """

    def __init__(
        self,
        *,
        weights: np.ndarray,
        means: np.ndarray,
        covariances: np.ndarray,
        matrices: np.ndarray,
        eps: float,
        reg_covar: float,
    ) -> None:
        super().__init__()
        as64 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
        self.eps = eps
        self.reg_covar = reg_covar
        n = means.shape[1]
        # Sigma = C C^T + r I: start from the mixture's own covariance, minus half the floor
        # scikit-learn already added to it (all of it could leave a singular matrix).
        base = covariances - 0.5 * reg_covar * np.eye(n)
        chol = np.linalg.cholesky(base)
        diag = np.diagonal(chol, axis1=-2, axis2=-1)
        self.logits = nn.Parameter(as64(np.log(weights)))
        self.means = nn.Parameter(as64(means))
        self.chol_lower = nn.Parameter(as64(np.tril(chol, -1)))
        self.chol_log_diag = nn.Parameter(as64(np.log(diag)))
        factors, skew = _project_stable(matrices, eps)
        self.factors = nn.Parameter(as64(factors))
        self.skew = nn.Parameter(as64(skew))

    def covariances(self) -> Tensor:
        r""":math:`\Sigma_k = C_k C_k^\top + r I`, shape (K, n, n)."""
        chol = torch.tril(self.chol_lower, -1) + torch.diag_embed(self.chol_log_diag.exp())
        eye = torch.eye(chol.shape[-1], dtype=chol.dtype)
        return chol @ chol.transpose(-1, -2) + self.reg_covar * eye

    def matrices(self) -> Tensor:
        r""":math:`A_k = -(L_k L_k^\top + \epsilon I) + (S_k - S_k^\top)`, shape (K, n, n)."""
        eye = torch.eye(self.factors.shape[-1], dtype=self.factors.dtype)
        sym = self.factors @ self.factors.transpose(-1, -2) + self.eps * eye
        return -sym + (self.skew - self.skew.transpose(-1, -2))

    def forward(self, x: Tensor) -> Tensor:
        """The SEDS field at positions (N, n), shape (N, n)."""
        chol = torch.linalg.cholesky(self.covariances())
        eye = torch.eye(chol.shape[-1], dtype=chol.dtype).expand_as(chol)
        # U = C^{-T}, upper triangular: U U^T = Sigma^{-1}, as log_responsibilities expects.
        factors = torch.linalg.solve_triangular(chol, eye, upper=False).transpose(-1, -2)
        log_weights = torch.log_softmax(self.logits, dim=0)
        gamma = log_responsibilities(x, log_weights, self.means, factors).exp()
        return blend(x, gamma, self.matrices())


def _optimise(params: _SEDSParameters, x: Tensor, v: Tensor, iterations: int) -> dict:
    r"""Minimises the velocity MSE over ``params`` in place by full-batch L-BFGS.

    If the optimisation fails (an exception, a non-finite loss) or ends worse than it
    started, the initial parameters are restored: a fit never returns worse than its start.

    Arguments:
        params: The parametrisation, initialised.
        x: Training positions in model coordinates, shape (N, n).
        v: Their velocities, shape (N, n).
        iterations: Maximum L-BFGS iterations.

    Returns:
        A record: status, iterations, loss evaluations, initial and final MSE
        :math:`\frac1N \sum_i \|\dot x_i - f(x_i)\|^2`.
    """
    loss_fn = lambda: ((params(x) - v) ** 2).sum(-1).mean()  # noqa: E731
    with torch.no_grad():
        initial_mse = float(loss_fn())
    state = {k: t.detach().clone() for k, t in params.state_dict().items()}
    optimizer = torch.optim.LBFGS(
        params.parameters(),
        lr=1.0,
        max_iter=max(1, iterations),
        history_size=20,
        tolerance_grad=1e-10,
        tolerance_change=1e-14,
        line_search_fn="strong_wolfe",
    )

    def closure() -> Tensor:
        optimizer.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    status = "ok"
    try:
        optimizer.step(closure)
    except RuntimeError as error:  # e.g. a Cholesky factorisation that failed
        status = f"failed ({error.__class__.__name__}); initial parameters kept"
    with torch.no_grad():
        try:
            final_mse = float(loss_fn())
        except RuntimeError:
            final_mse = math.nan
    if not final_mse <= initial_mse:
        params.load_state_dict(state)
        final_mse = initial_mse
        status = "no improvement; initial parameters kept" if status == "ok" else status
    # L-BFGS keeps its counters in the state of its first parameter.
    counters = optimizer.state_dict()["state"].get(0, {})
    return {
        "status": status,
        "iterations": int(counters.get("n_iter", 0)),
        "evaluations": int(counters.get("func_evals", 0)),
        "mse_initial": initial_mse,
        "mse": final_mse,
    }


@dataclass(frozen=True)
class SEDS:
    """SEDS fitted by L-BFGS on the velocity MSE, stable by construction.

    Attributes:
        name: "seds".
        description: One line for tables.
        has_lyapunov: True: V = |x|^2.
        components: A fixed K, or None to choose it by BIC over 1..``max_components``.
        max_components: K_max of the BIC search (on the joint (x, xdot) mixture).
        eps: epsilon of A_k + A_k^T <= -2 eps I, in model units (1 / model time).
        reg_covar: Floor r added to the covariances (squared model units).
        max_samples: Training samples used for the initial mixture (0: all); the
            optimisation uses all of them.
        steps: L-BFGS iterations (the ``steps`` argument of :meth:`fit` overrides it).
    """

    name: str = "seds"
    description: str = "SEDS: Gaussian mixture regression of stable linear systems (V = |x|^2)"
    has_lyapunov: ClassVar[bool] = True
    spaces: ClassVar[tuple[type[Space], ...]] = (Euclidean,)
    components: int | None = None
    max_components: int = 15
    eps: float = 0.02
    reg_covar: float = 1e-4
    max_samples: int = 2000
    steps: int = 500

    def fit(
        self,
        demos: Demonstrations,
        split: Split,
        *,
        seed: int = 0,
        steps: int | None = None,
        progress: bool = False,
    ) -> Fitted:
        """Fits a :class:`SEDSPolicy`; ``steps`` overrides the L-BFGS iterations.

        Raises:
            SNDSError: If the fitted matrices fail the stability verification (not expected:
                the parametrisation makes them stable).
        """
        refuse_other_spaces(self.name, self.spaces, demos)
        with single_threaded():
            return self._fit(demos, split, seed=seed, steps=steps)

    def _fit(self, demos: Demonstrations, split: Split, *, seed: int, steps: int | None) -> Fitted:
        """The fit itself (see :meth:`fit`), with one BLAS / OpenMP thread."""
        normalization = Normalization.fit(demos)
        samples = make_samples(demos, normalization, split, window=0)
        x, v = samples.positions, samples.velocities
        n = demos.dim
        iterations = self.steps if steps is None else steps
        rng = np.random.default_rng(seed)
        require("sklearn.mixture")  # before the clock, and the install hint if missing
        # The first optimiser of a process imports torch's compiler stack (seconds, on a
        # busy machine); that is not fitting, and snds.train.fit starts its clock after it too.
        torch.optim.LBFGS([torch.zeros(1, requires_grad=True)])
        start = time.perf_counter()
        few = subsample(len(x), self.max_samples, rng)
        joint = np.concatenate([x.numpy(), v.numpy()], axis=1)[few]
        mixture = fit_mixture(
            joint,
            components=self.components,
            max_components=self.max_components,
            seed=seed,
            reg_covar=self.reg_covar,
        )
        positions = mixture.marginal(n)
        # The unconstrained least-squares A_k for these responsibilities, then the closest
        # admissible ones: a start near the data that already satisfies the constraints.
        design = design_matrix(x.numpy(), positions.responsibilities(x.numpy()))
        gram = design.T @ design + 1e-8 * len(design) * np.eye(design.shape[1])
        initial = matrices_from_coefficients(np.linalg.solve(gram, design.T @ v.numpy()))
        params = _SEDSParameters(
            weights=positions.weights,
            means=positions.means,
            covariances=positions.covariances,
            matrices=initial,
            eps=self.eps,
            reg_covar=self.reg_covar,
        )
        optimisation = _optimise(params, x, v, iterations)
        with torch.no_grad():
            weights = torch.softmax(params.logits, 0).numpy()
            covariances = params.covariances().numpy()
            matrices = params.matrices().numpy()
            means = params.means.detach().numpy()
        policy = SEDSPolicy(
            dim=n,
            normalization=normalization,
            config=MixtureConfig(components=mixture.components),
        )
        margin = policy.set_fitted(
            weights=weights,
            means=means,
            covariances=covariances,
            matrices=matrices,
            lyapunov_matrix=np.eye(n),
        )
        seconds = time.perf_counter() - start
        record = {
            "seds": {
                "settings": {
                    k: val for k, val in asdict(self).items() if k not in ("name", "description")
                },
                "components": mixture.components,
                "bic": {str(k): val for k, val in mixture.bic.items()},
                "samples": len(x),
                "samples_mixture": len(few),
                **optimisation,
                "margin": margin,
                "seed": seed,
            }
        }
        return Fitted(policy=policy, seconds=seconds, record=record)
