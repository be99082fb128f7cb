r"""What every method of the library learns: :class:`Policy`, a velocity field in user units
computed in the task's model coordinates, with a Lyapunov function where the method has one.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from typing import Any, ClassVar, NamedTuple, Protocol

import numpy as np
import torch
from torch import Tensor, nn

from snds.data.demonstrations import Normalization
from snds.spaces import Euclidean, Space

__all__ = ["FieldTerms", "LyapunovFunction", "Policy", "float64_copy"]


class FieldTerms(NamedTuple):
    """A policy's field at states in model coordinates and what it is made of.

    Attributes:
        field: The policy, shape (*, n).
        nominal: The nominal field it projects, (*, n); None if it projects none.
        value: V, shape (*,); None without a Lyapunov function.
        grad: The gradient of V, (*, n); None without a Lyapunov function.
    """

    field: Tensor
    nominal: Tensor | None
    value: Tensor | None
    grad: Tensor | None


class LyapunovFunction(Protocol):
    r"""What a policy's Lyapunov function offers the checks, in model coordinates.

    Attributes:
        quadratic: A floor :math:`d \ge 0` with :math:`V(x) \ge d \|x\|^2` (0 if none is
            known); the stability check stops integrating a rollout once it is provably
            settled in :math:`\{V < d r^2\}`, which needs :math:`d > 0`.
    """

    quadratic: float

    def value_and_grad(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """V, shape (*,), and its gradient, shape (*, n), at states (*, n)."""
        ...

    def __call__(self, x: Tensor) -> Tensor:
        """V at states (*, n), shape (*,)."""
        ...


class Policy(nn.Module, ABC):
    r"""A velocity field in user units, computed in the task's model coordinates.

    States live in :attr:`space` (positions in :math:`\mathbb{R}^n` by default; poses for
    :class:`~snds.se3.PosePolicy`). Model coordinates put the target at 0 with extent 1 and
    top speed 1 (see :class:`~snds.data.Normalization`); :meth:`forward` maps user states
    there (:meth:`to_model`), evaluates :meth:`field` and maps the velocities back
    (:meth:`velocity_to_user`). A subclass implements :meth:`field`; one
    with a stability guarantee sets :attr:`lyapunov` to its Lyapunov function and
    :attr:`stable` to True, and states its guarantee, which the stability checks test:
    :math:`\nabla V^\top \pi \le -a(x)` with :meth:`decay` :math:`a \ge 0`.

    A subclass is saved and loaded by :mod:`snds.io` from its :attr:`kind`, its ``config``
    (a frozen dataclass with ``to_dict``, the class in :attr:`config_class`) and its state
    dict: ``cls(dim=..., normalization=..., config=...)`` must rebuild every tensor shape.

    Arguments:
        dim: Dimension n of the model coordinates (the state dimension for positions).
        normalization: The task's affine map of space and time.
    """

    #: Key of the class in :data:`snds.methods.POLICY_KINDS`, written into model.json.
    kind: ClassVar[str]
    #: The frozen dataclass of the constructor's ``config``.
    config_class: ClassVar[type]
    config: Any
    # Set by subclasses (a submodule, or None); not a class default, which would shadow the
    # submodule that nn.Module keeps outside the instance dict.
    lyapunov: LyapunovFunction | None

    def __init__(self, *, dim: int, normalization: Normalization) -> None:
        super().__init__()
        self.dim = dim
        self.normalization = normalization
        self.register_buffer("center", torch.tensor(normalization.center, dtype=torch.float32))
        self.length = normalization.length
        self.time = normalization.time

    @property
    def method(self) -> str:
        """The name of the method that made it (a key of :data:`snds.methods.METHODS`)."""
        return self.kind

    @property
    def space(self) -> Space:
        r"""The space of the states :meth:`forward` takes: :math:`\mathbb{R}^n` by default."""
        return Euclidean(self.dim)

    @property
    def stable(self) -> bool:
        """Whether the policy carries a Lyapunov function (and so a guarantee to check)."""
        return getattr(self, "lyapunov", None) is not None

    @abstractmethod
    def field(self, x: Tensor) -> Tensor:
        """The policy in model coordinates, (*, n) -> (*, n)."""

    def nominal(self, x: Tensor) -> Tensor:
        """The field before any stabilisation, (*, n) -> (*, n); the field itself by default.

        The decrease check scales its rounding tolerance by it (see
        :func:`snds.stability.decrease_violations`).
        """
        return self.field(x)

    def field_and_nominal(self, x: Tensor) -> tuple[Tensor, Tensor | None]:
        """The field, (*, n), and the nominal field it projects (None if it projects none)."""
        return self.field(x), None

    def field_terms(self, x: Tensor) -> FieldTerms:
        """The field at states (*, n) in model coordinates with what it is made of, from one
        pass where the field needs V anyway: V and its gradient for a policy with a Lyapunov
        function (None otherwise), and the nominal field (None if it projects none)."""
        field = self.field(x)
        if not self.stable:
            return FieldTerms(field, None, None, None)
        value, grad = self.lyapunov.value_and_grad(x)
        return FieldTerms(field, None, value, grad)

    def velocity_and_value(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`forward`'s velocities (*, space.tangent_dim) and V in model coordinates
        (*,) at user states (*, space.dim), in the policy's dtype: what a guarded step needs
        at the state it reaches (see :func:`snds.rollout.policy_guard`). Only for a policy
        with a Lyapunov function."""
        z = self.to_model(x)
        field, value = self._field_and_value(z)
        return self.velocity_to_user(z, field), value

    def _field_and_value(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """The field and V at model states z, without V's gradient where the field does not
        need it (two passes here; one for a policy whose field is made from V)."""
        return self.field(z), self.lyapunov(z)

    def decay(self, v: Tensor, x: Tensor) -> Tensor:
        """The guaranteed decrease rate a(x) >= 0 of V, shape (*,); 0 by default.

        Arguments:
            v: V at the states, shape (*,).
            x: The states in model coordinates, shape (*, n).
        """
        return torch.zeros_like(v)

    def set_anchors(self, positions: Tensor) -> None:
        """Shows the policy its training states in model coordinates, shape (N, n), before a
        fit (see :attr:`~snds.policy.PolicyConfig.anchors`); a policy without anchors ignores
        them."""

    def to_model(self, x: Tensor) -> Tensor:
        """User states (*, space.dim) to model coordinates (*, n)."""
        return (x - self.center.to(x.dtype)) / self.length

    @property
    def target(self) -> np.ndarray:
        """The target state x* in user units, shape (space.dim,), float64."""
        return np.asarray(self.normalization.center, dtype=np.float64)

    def extents(self) -> np.ndarray:
        """The demonstrations' extent in each error component of :attr:`space`
        (:meth:`~snds.spaces.Space.errors`), user units, shape (k,): the positions' first."""
        return np.array([self.normalization.extent])

    def chart_scales(self) -> np.ndarray:
        """User units per unit of the chart that :attr:`normalization` maps, one per error
        component of :attr:`space`, shape (k,): 1 for positions (the chart is the user
        space itself)."""
        return np.ones(len(self.space.error_names))

    def model_scale(self) -> np.ndarray:
        """How far one unit of model coordinates reaches in each error component of
        :attr:`space` (:meth:`~snds.spaces.Space.errors`), user units, shape (k,): a state
        within model distance r of the target is within r times this of it."""
        return self.chart_scales() * self.length

    def velocity_to_user(self, z: Tensor, velocity: Tensor) -> Tensor:
        """Model velocities (*, n) at model coordinates z (*, n) to user velocities
        (*, space.tangent_dim)."""
        return velocity * (self.length / self.time)

    def training_demonstrations(self, demos: Any) -> Any:
        """The demonstrations in the coordinates that :attr:`normalization` maps to model
        coordinates, as :func:`snds.train.fit` trains on them: ``demos`` themselves for
        positions."""
        return demos

    def forward(self, x: Tensor) -> Tensor:
        """Velocities (*, space.tangent_dim) in user units at states (*, space.dim) in user
        units.

        The policy computes in its own precision (that of its weights); states of another
        dtype (float32 into a float64 model, integers, ...) are cast to it, so the velocities
        are in the model's precision.
        """
        dtype = self.center.dtype
        # A Python-level test, so an export traced in the model's dtype holds no Cast node.
        if x.dtype != dtype:
            x = x.to(dtype)
        z = self.to_model(x)
        return self.velocity_to_user(z, self.field(z))

    @torch.no_grad()
    def predict(self, x: np.ndarray, *, chunk: int = 65_536) -> np.ndarray:
        """NumPy convenience: velocities (*, space.tangent_dim) at states (*, space.dim), both
        in user units, evaluated ``chunk`` states at a time (bounds the memory of the
        networks' activations)."""
        dtype, device = self.center.dtype, self.center.device
        array = np.asarray(x)
        flat = array.reshape(-1, array.shape[-1])
        width = self.space.tangent_dim
        out = np.empty((len(flat), width), dtype=torch.empty(0, dtype=dtype).numpy().dtype)
        for begin in range(0, len(flat), chunk):
            # A copy: demonstrations' arrays are read-only, which torch.as_tensor warns about.
            rows = torch.tensor(flat[begin : begin + chunk], dtype=dtype, device=device)
            out[begin : begin + chunk] = self(rows).cpu().numpy()
        return out.reshape(*array.shape[:-1], width)


def float64_copy(policy: Policy) -> Policy:
    """A float64 copy of a policy in eval mode, for checks; the original is not changed."""
    return copy.deepcopy(policy).to(torch.float64).eval()
