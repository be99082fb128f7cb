r"""Gaussian mixtures of linear systems: the model shared by LPV-DS and SEDS.

Both baselines learn, in model coordinates (target at 0, extent 1, top speed 1),

.. math:: \dot x = \sum_{k=1}^K \gamma_k(x) A_k x, \qquad
    \gamma_k(x) = \frac{\pi_k \mathcal N(x; \mu_k, \Sigma_k)}
    {\sum_j \pi_j \mathcal N(x; \mu_j, \Sigma_j)},

a blend of linear systems through the target weighted by the posterior responsibilities of a
Gaussian mixture over positions, with a quadratic Lyapunov function :math:`V = x^\top P x`.
If every :math:`A_k^\top P + P A_k \preceq -c I` with :math:`c > 0`, then for any convex
combination :math:`\dot V = \sum_k \gamma_k x^\top (A_k^\top P + P A_k) x \le -c \|x\|^2`,
so the target is the only equilibrium and it is globally asymptotically (indeed
exponentially) stable. The methods differ in how they fit the numbers:
:mod:`snds.baselines.lpvds` and :mod:`snds.baselines.seds`.

This module holds the parts they share: :class:`MixtureLinearPolicy` (the field, in torch),
:class:`QuadraticLyapunov`, :func:`log_responsibilities`, the verification
:func:`stability_margin`, and the scikit-learn mixture fit with BIC selection
(:func:`fit_mixture`; scikit-learn is imported only there).
"""

from __future__ import annotations

import contextlib
import importlib
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from types import ModuleType

import numpy as np
import torch
from torch import Tensor, nn

from snds.data.demonstrations import Normalization
from snds.errors import SNDSError
from snds.policy import Policy

__all__ = [
    "MixtureConfig",
    "MixtureFit",
    "MixtureLinearPolicy",
    "QuadraticLyapunov",
    "blend",
    "design_matrix",
    "fit_mixture",
    "log_responsibilities",
    "matrices_from_coefficients",
    "precision_factor",
    "require",
    "single_threaded",
    "stability_margin",
    "subsample",
]


def require(module: str) -> ModuleType:
    """Imports a module of the ``baselines`` extra, or says how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise SNDSError(
            f"this baseline needs {module.split('.')[0]}: pip install 'snds[baselines]'"
        ) from error


@contextlib.contextmanager
def single_threaded() -> Iterator[None]:
    """One BLAS / OpenMP thread (NumPy, scikit-learn) inside the block.

    The fits work on a few thousand points and matrices of a few dozen rows: threads cost far
    more in synchronisation than they save, and benchmark runs already fill the cores side
    by side.
    """
    with require("threadpoolctl").threadpool_limits(limits=1):
        yield


def log_responsibilities(
    x: Tensor, log_weights: Tensor, means: Tensor, precision_factors: Tensor
) -> Tensor:
    r"""Log posterior responsibilities :math:`\log \gamma_k(x)` of a Gaussian mixture.

    With :math:`\Sigma_k^{-1} = U_k U_k^\top` and :math:`U_k` upper triangular with a positive
    diagonal (scikit-learn's ``precisions_cholesky_``),

    .. math:: \log \pi_k \mathcal N(x; \mu_k, \Sigma_k) = \log \pi_k + \sum_i \log (U_k)_{ii}
        - \tfrac12 \|U_k^\top (x - \mu_k)\|^2 - \tfrac n2 \log 2\pi,

    normalised over k by log-sum-exp (the constant cancels). Far from the data the quadratic
    terms are huge and all of one sign; subtracting their maximum keeps the result finite, so
    the responsibilities stay a convex combination (finite, summing to 1) at any distance.

    Arguments:
        x: States, shape (*, n).
        log_weights: Log mixture weights, shape (K,).
        means: Component means, shape (K, n).
        precision_factors: Upper-triangular factors of the precisions, shape (K, n, n).

    Returns:
        :math:`\log \gamma_k(x)`, shape (*, K).
    """
    k, n = means.shape
    # (x - mu_k)^T U_k for all k as one (N, n) x (n, K n) product: batched per-component
    # products of 2 x 2 matrices cost 50x more in kernel launches than the arithmetic.
    stacked = precision_factors.permute(1, 0, 2).reshape(n, k * n)  # [i, k n + j] = U_k[i, j]
    offsets = (means.unsqueeze(-2) @ precision_factors).squeeze(-2)  # mu_k^T U_k, (K, n)
    whitened = (x.reshape(-1, n) @ stacked).reshape(-1, k, n) - offsets
    log_det = torch.log(torch.diagonal(precision_factors, dim1=-2, dim2=-1)).sum(-1)  # (K,)
    log_joint = log_weights + log_det - 0.5 * (whitened * whitened).sum(-1)
    return torch.log_softmax(log_joint, dim=-1).reshape(*x.shape[:-1], k)


def blend(x: Tensor, gamma: Tensor, matrices: Tensor) -> Tensor:
    r""":math:`\sum_k \gamma_k A_k x` at states (*, n), weights (*, K), matrices (K, n, n).

    Returns:
        The blended velocities, shape (*, n).
    """
    k, n, _ = matrices.shape
    # One (N, n) x (n, K n) product for every A_k x, as in log_responsibilities.
    stacked = matrices.permute(2, 0, 1).reshape(n, k * n)  # [j, k n + i] = A_k[i, j]
    per_component = (x.reshape(-1, n) @ stacked).reshape(-1, k, n)
    weights = gamma.reshape(-1, 1, k)
    return (weights @ per_component).reshape(x.shape)


def precision_factor(covariances: np.ndarray) -> np.ndarray:
    r"""Upper-triangular :math:`U` with :math:`U U^\top = \Sigma^{-1}`, shape (K, n, n).

    With the Cholesky factor :math:`\Sigma = C C^\top`, :math:`U = C^{-\top}`.
    """
    chol = np.linalg.cholesky(covariances)
    eye = np.broadcast_to(np.eye(covariances.shape[-1]), covariances.shape)
    return np.swapaxes(np.linalg.solve(chol, eye), -1, -2)


def stability_margin(matrices: np.ndarray, lyapunov_matrix: np.ndarray) -> float:
    r"""The verified decrease rate :math:`c = \min_k -\lambda_{\max}(A_k^\top P + P A_k)`.

    Positive iff every linear system decreases :math:`V = x^\top P x` strictly; then
    :math:`\dot V \le -c \|x\|^2` for the whole mixture. Computed in float64 from the numbers
    the policy stores, not from what a solver reports.

    Arguments:
        matrices: The :math:`A_k`, shape (K, n, n).
        lyapunov_matrix: The symmetric :math:`P`, shape (n, n).
    """
    a = np.asarray(matrices, dtype=np.float64)
    p = np.asarray(lyapunov_matrix, dtype=np.float64)
    lie = np.swapaxes(a, -1, -2) @ p + p @ a
    return float(-np.linalg.eigvalsh(0.5 * (lie + np.swapaxes(lie, -1, -2))).max())


class QuadraticLyapunov(nn.Module):
    r""":math:`V(x) = x^\top P x` with a symmetric positive definite :math:`P`, shape (n, n).

    :math:`P` is a frozen parameter, so it is saved with the policy and follows its dtype.

    Arguments:
        dim: State dimension n; :math:`P = I` until set.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.matrix = nn.Parameter(torch.eye(dim), requires_grad=False)

    @property
    def quadratic(self) -> float:
        r"""The floor :math:`\lambda_{\min}(P)` of :math:`V(x) \ge \lambda_{\min} \|x\|^2`."""
        return float(torch.linalg.eigvalsh(self.matrix.detach().double()).min())

    def forward(self, x: Tensor) -> Tensor:
        """V at states (*, n), shape (*,)."""
        return ((x @ self.matrix) * x).sum(-1)

    def value_and_grad(self, x: Tensor) -> tuple[Tensor, Tensor]:
        r"""V, shape (*,), and :math:`\nabla V = 2 P x`, shape (*, n), at states (*, n)."""
        px = x @ self.matrix  # P is symmetric: x^T P = (P x)^T
        return (px * x).sum(-1), 2.0 * px


def _frozen(tensor: Tensor) -> nn.Parameter:
    # Fitted numbers are parameters (so they land in safetensors, follow .to() and count in
    # .parameters()), but no optimiser should move them after the fit.
    return nn.Parameter(tensor, requires_grad=False)


@dataclass(frozen=True, kw_only=True)
class MixtureConfig:
    """Architecture of a mixture-of-linear-systems policy (LPV-DS, SEDS); saved beside its
    weights.

    Attributes:
        components: Number of mixture components K.
    """

    components: int = 1

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


class MixtureLinearPolicy(Policy):
    r"""The field :math:`\dot x = \sum_k \gamma_k(x) A_k x` with :math:`V = x^\top P x`.

    Every fitted number is a frozen parameter: the log mixture weights (K,), means (K, n),
    upper-triangular precision factors (K, n, n) (see :func:`log_responsibilities`), the
    :math:`A_k` (K, n, n), :math:`P` (in :attr:`lyapunov`) and the verified rate :math:`c`
    of :math:`\dot V \le -c \|x\|^2`. Before a fit it is the stable field :math:`-x`.

    Arguments:
        dim: State dimension n.
        normalization: The task's affine map of space and time.
        config: The number of mixture components K.
        seed: Unused (nothing is random before the fit); kept for the common signature.
    """

    config_class = MixtureConfig

    def __init__(
        self, *, dim: int, normalization: Normalization, config: MixtureConfig, seed: int = 0
    ) -> None:
        super().__init__(dim=dim, normalization=normalization)
        self.config = config
        components = config.components
        if components < 1:
            raise ValueError(f"components must be >= 1, got {components}")
        eye = torch.eye(dim).expand(components, dim, dim)
        self.log_weights = _frozen(torch.full((components,), -math.log(components)))
        self.means = _frozen(torch.zeros(components, dim))
        self.precision_factors = _frozen(eye.clone())
        self.matrices = _frozen(-eye.clone())
        self.rate = _frozen(torch.zeros(()))
        self.lyapunov = QuadraticLyapunov(dim)

    @property
    def components(self) -> int:
        """Number of mixture components K."""
        return self.log_weights.shape[0]

    def responsibilities(self, x: Tensor) -> Tensor:
        r""":math:`\gamma_k(x)` at states (*, n) in model coordinates, shape (*, K)."""
        return log_responsibilities(x, self.log_weights, self.means, self.precision_factors).exp()

    def field(self, x: Tensor) -> Tensor:
        """The policy in model coordinates, (*, n) -> (*, n)."""
        return blend(x, self.responsibilities(x), self.matrices)

    def decay(self, v: Tensor, x: Tensor) -> Tensor:
        r"""The guaranteed decrease :math:`a(x) = c \|x\|^2` of V, shape (*,).

        Arguments:
            v: V at the states, shape (*,) (unused: the bound is in :math:`\|x\|^2`).
            x: The states in model coordinates, shape (*, n).
        """
        return self.rate * (x * x).sum(-1)

    @torch.no_grad()
    def set_fitted(
        self,
        *,
        weights: np.ndarray,
        means: np.ndarray,
        covariances: np.ndarray,
        matrices: np.ndarray,
        lyapunov_matrix: np.ndarray,
    ) -> float:
        r"""Stores fitted numbers (in float64) after verifying the stability conditions.

        Arguments:
            weights: Mixture weights, shape (K,), positive.
            means: Component means over positions, shape (K, n).
            covariances: Their covariances, shape (K, n, n), positive definite.
            matrices: The :math:`A_k`, shape (K, n, n).
            lyapunov_matrix: :math:`P`, shape (n, n), symmetrised here.

        Returns:
            The verified margin :math:`c > 0` of :func:`stability_margin`.

        Raises:
            SNDSError: If :math:`P` is not positive definite or some
                :math:`A_k^\top P + P A_k` is not negative definite; nothing is changed then.
        """
        p = 0.5 * (lyapunov_matrix + lyapunov_matrix.T)
        if np.linalg.eigvalsh(p).min() <= 0:
            raise SNDSError("the Lyapunov matrix P is not positive definite")
        margin = stability_margin(matrices, p)
        if not margin > 0:
            raise SNDSError(f"stability conditions violated: max eigenvalue {-margin:.3g} >= 0")
        self.double()
        as64 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
        self.log_weights.copy_(as64(np.log(weights)))
        self.means.copy_(as64(means))
        self.precision_factors.copy_(as64(precision_factor(covariances)))
        self.matrices.copy_(as64(matrices))
        self.lyapunov.matrix.copy_(as64(p))
        # A hair under the verified margin: the decrease check compares against it in
        # floating point, and the claim must stay true after rounding.
        self.rate.fill_((1.0 - 1e-6) * margin)
        return margin


@dataclass(frozen=True)
class MixtureFit:
    """A Gaussian mixture chosen by BIC.

    Attributes:
        weights: Mixture weights, shape (K,).
        means: Means, shape (K, d).
        covariances: Covariances, shape (K, d, d).
        bic: BIC of every number of components tried, by K.
    """

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    bic: dict[int, float]

    @property
    def components(self) -> int:
        """The chosen K."""
        return len(self.weights)

    def marginal(self, dims: int) -> MixtureFit:
        """The mixture of the first ``dims`` coordinates (e.g. positions of a joint (x, v) fit)."""
        return MixtureFit(
            self.weights, self.means[:, :dims], self.covariances[:, :dims, :dims], self.bic
        )

    def responsibilities(self, x: np.ndarray) -> np.ndarray:
        """The posterior responsibilities over positions (*, d), shape (*, K).

        Computed by :func:`log_responsibilities` in float64, the same code the policy runs,
        so that a fit that uses them agrees with the field it produces.
        """
        as64 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
        with torch.no_grad():
            log_gamma = log_responsibilities(
                as64(x),
                as64(np.log(self.weights)),
                as64(self.means),
                as64(precision_factor(self.covariances)),
            )
        return log_gamma.exp().numpy()


def fit_mixture(
    points: np.ndarray,
    *,
    components: int | None,
    max_components: int,
    seed: int,
    reg_covar: float,
) -> MixtureFit:
    r"""Fits full-covariance Gaussian mixtures (scikit-learn EM) and keeps the lowest BIC.

    :math:`\mathrm{BIC} = -2 \log \hat L + p \log N` with p free parameters; K runs over
    1..``max_components`` (never more than the points), or is ``components`` if given.

    Arguments:
        points: The data, shape (N, d).
        components: A fixed K, or None to choose by BIC.
        max_components: The largest K tried by BIC.
        seed: Seed of the k-means initialisation.
        reg_covar: Added to every covariance's diagonal (in squared model units): a floor on
            the components' width, so the blend stays smooth across a thin demonstration.
    """
    gaussian_mixture = require("sklearn.mixture").GaussianMixture
    candidates = [components] if components is not None else range(1, max_components + 1)
    best, best_bic, bic = None, math.inf, {}
    with single_threaded():
        for k in candidates:
            if k > len(points):
                break
            gmm = gaussian_mixture(
                n_components=k, covariance_type="full", reg_covar=reg_covar, random_state=seed
            ).fit(points)
            bic[k] = float(gmm.bic(points))
            if bic[k] < best_bic:
                best, best_bic = gmm, bic[k]
    if best is None:
        raise SNDSError(f"cannot fit a mixture to {len(points)} points")
    return MixtureFit(best.weights_, best.means_, best.covariances_, bic)


def design_matrix(x: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    r"""The design of the least squares for the :math:`A_k`, shape (N, K n).

    Row i is :math:`(\gamma_{i1} x_i^\top, \dots, \gamma_{iK} x_i^\top)`, so with
    coefficients :math:`\theta_{kn + l, j} = (A_k)_{jl}`, shape (K n, n), the prediction
    :math:`\sum_k \gamma_k(x_i) A_k x_i` is row i of ``design @ theta``.

    Arguments:
        x: Positions, shape (N, n).
        gamma: Responsibilities at them, shape (N, K).
    """
    return (gamma[:, :, None] * x[:, None, :]).reshape(len(x), -1)


def matrices_from_coefficients(theta: np.ndarray) -> np.ndarray:
    """The :math:`A_k`, shape (K, n, n), from the coefficients (K n, n) of
    :func:`design_matrix`."""
    n = theta.shape[1]
    return np.swapaxes(theta.reshape(-1, n, n), -1, -2)


def subsample(count: int, limit: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of at most ``limit`` of ``count`` samples, uniformly without replacement."""
    if limit <= 0 or count <= limit:
        return np.arange(count)
    return np.sort(rng.choice(count, size=limit, replace=False))
