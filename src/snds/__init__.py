"""snds: globally stable neural motion policies learned from demonstrations.

The pipeline, one module each: demonstrations (:mod:`snds.data`) -> networks
(:mod:`snds.nn`) -> stable policy (:mod:`snds.policy`) -> loss (:mod:`snds.losses`) ->
training (:mod:`snds.train`) -> rollouts (:mod:`snds.rollout`) -> metrics and stability
(:mod:`snds.metrics`, :mod:`snds.stability`, :mod:`snds.evaluate`) -> files (:mod:`snds.models`)
and plots (:mod:`snds.plotting`), with the CLI (:mod:`snds.cli`) on top.
"""

from snds._version import __version__
from snds.batched import fit_many
from snds.errors import DataError, ModelFileError, SNDSError
from snds.policy import PolicyConfig, StablePolicy, project
from snds.recipes import RECIPES, Recipe
from snds.train import TrainConfig, TrainingError, fit

__all__ = [
    "DataError",
    "ModelFileError",
    "PolicyConfig",
    "RECIPES",
    "Recipe",
    "SNDSError",
    "StablePolicy",
    "TrainConfig",
    "TrainingError",
    "__version__",
    "fit",
    "fit_many",
    "project",
]
