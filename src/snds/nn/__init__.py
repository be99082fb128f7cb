"""Networks: the nominal MLP, the input-convex network and the Lyapunov function."""

from snds.nn.icnn import CONVEX_ACTIVATIONS, ICNN
from snds.nn.lyapunov import Lyapunov
from snds.nn.mlp import ACTIVATIONS, MLP, FourierFeatures

__all__ = ["ACTIVATIONS", "CONVEX_ACTIVATIONS", "ICNN", "MLP", "FourierFeatures", "Lyapunov"]
