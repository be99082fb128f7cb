"""snds: globally stable neural motion policies learned from demonstrations.

The pipeline, one module each: demonstrations (:mod:`snds.data`) -> networks
(:mod:`snds.nn`) -> stable policy (:mod:`snds.policy`) -> loss (:mod:`snds.losses`) ->
training (:mod:`snds.train`, hooks in :mod:`snds.callbacks`) -> rollouts (:mod:`snds.rollout`)
-> metrics and stability (:mod:`snds.metrics`, :mod:`snds.stability`, :mod:`snds.evaluate`:
``snds.evaluate.evaluate``, since a function of that name would hide its module) -> files
(:mod:`snds.models`) and plots (:mod:`snds.plotting`); :func:`snds.run.train_run` runs them all
as ``snds train`` does, with the CLI (:mod:`snds.cli`) and the page (:mod:`snds.app`) on top.
"""

from snds._version import __version__
from snds.batched import fit_many
from snds.callbacks import Callback
from snds.data import (
    DataSource,
    Demonstrations,
    load_demonstrations,
    load_lasa,
    no_split,
    split_samples,
)
from snds.data.poses import load_poses
from snds.errors import DataError, ModelFileError, SNDSError
from snds.evaluate import Evaluation
from snds.method import make_policy
from snds.models import load_model, save_model
from snds.phase import Phase, start_state
from snds.policy import Policy, PolicyConfig, StablePolicy, project
from snds.recipes import RECIPES, Recipe
from snds.run import Run, SplitConfig, train_run
from snds.se3 import PosePolicy
from snds.spaces import SE3, Euclidean, Phased
from snds.stability import CheckConfig, check_stability
from snds.train import TrainConfig, TrainingError, TrainResult, fit

__all__ = [
    "SE3",
    "Callback",
    "CheckConfig",
    "DataError",
    "DataSource",
    "Demonstrations",
    "Euclidean",
    "Evaluation",
    "ModelFileError",
    "Phase",
    "Phased",
    "Policy",
    "PolicyConfig",
    "PosePolicy",
    "RECIPES",
    "Recipe",
    "Run",
    "SNDSError",
    "SplitConfig",
    "StablePolicy",
    "TrainConfig",
    "TrainResult",
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
    "train_run",
]
