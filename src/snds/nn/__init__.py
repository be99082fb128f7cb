"""Networks: the nominal MLP, the input-convex network, the coupling flow and the Lyapunov
functions."""

from snds.nn.flow import EuclideanizingFlow
from snds.nn.icnn import CONVEX_ACTIVATIONS, ICNN
from snds.nn.lyapunov import Lyapunov, WarpedLyapunov
from snds.nn.mlp import ACTIVATIONS, MLP, FourierFeatures

__all__ = [
    "ACTIVATIONS",
    "CONVEX_ACTIVATIONS",
    "ICNN",
    "MLP",
    "EuclideanizingFlow",
    "FourierFeatures",
    "Lyapunov",
    "WarpedLyapunov",
]
