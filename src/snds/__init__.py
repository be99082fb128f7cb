"""snds: globally stable neural motion policies learned from demonstrations.

The pipeline, one module each: demonstrations (:mod:`snds.data`) -> networks
(:mod:`snds.nn`) -> stable policy (:mod:`snds.policy`) -> loss (:mod:`snds.losses`) ->
training (:mod:`snds.train`) -> rollouts (:mod:`snds.rollout`) -> metrics and stability
(:mod:`snds.metrics`, :mod:`snds.stability`, :mod:`snds.evaluate`; the package does not
re-export :func:`snds.evaluate.evaluate`, which would hide its module) -> files (:mod:`snds.models`)
and plots (:mod:`snds.plotting`), with the CLI (:mod:`snds.cli`) on top.
"""

from snds._version import __version__
from snds.batched import fit_many
from snds.data import load_demonstrations, load_lasa, no_split, split_samples
from snds.data.poses import load_poses
from snds.errors import DataError, ModelFileError, SNDSError
from snds.methods import make_policy
from snds.models import load_model, save_model
from snds.phase import Phase, start_state
from snds.policy import PolicyConfig, StablePolicy, project
from snds.recipes import RECIPES, Recipe
from snds.se3 import PosePolicy
from snds.spaces import SE3, Euclidean, Phased
from snds.stability import CheckConfig, check_stability
from snds.train import TrainConfig, TrainingError, fit

__all__ = [
    "SE3",
    "CheckConfig",
    "DataError",
    "Euclidean",
    "ModelFileError",
    "Phase",
    "Phased",
    "PolicyConfig",
    "PosePolicy",
    "RECIPES",
    "Recipe",
    "SNDSError",
    "StablePolicy",
    "TrainConfig",
    "TrainingError",
    "__version__",
    "check_stability",
    "fit",
    "fit_many",
    "load_demonstrations",
    "load_lasa",
    "load_model",
    "load_poses",
    "make_policy",
    "no_split",
    "project",
    "save_model",
    "split_samples",
    "start_state",
]
