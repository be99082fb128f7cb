"""snds: globally stable neural motion policies learned from demonstrations.

The pipeline, one module each: demonstrations (:mod:`snds.data`) -> networks
(:mod:`snds.nn`) -> stable policy (:mod:`snds.policy`) -> loss (:mod:`snds.losses`) ->
training (:mod:`snds.train`) -> rollouts (:mod:`snds.rollout`) -> metrics and stability
(:mod:`snds.metrics`, :mod:`snds.stability`, :mod:`snds.evaluate`) -> files (:mod:`snds.io`)
and plots (:mod:`snds.plotting`), with the CLI (:mod:`snds.cli`) on top.
"""

__version__ = "0.1.0"

from snds.batched import fit_many  # noqa: E402
from snds.errors import DataError, ModelFileError, SNDSError  # noqa: E402
from snds.policy import PolicyConfig, StablePolicy, project  # noqa: E402
from snds.train import TrainConfig, TrainingError, fit  # noqa: E402

__all__ = [
    "DataError",
    "ModelFileError",
    "PolicyConfig",
    "SNDSError",
    "StablePolicy",
    "TrainConfig",
    "TrainingError",
    "__version__",
    "fit",
    "fit_many",
    "project",
]
