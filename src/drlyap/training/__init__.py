"""Training a controller and its certificate, and proving what was trained.

* :class:`TrainConfig` (:mod:`drlyap.config`, resolved once against its system) and its sections
  (:mod:`drlyap.sections`: what builds the condition, the networks, the sampling, the region goal, the schedule);
* :mod:`~drlyap.training.states` -- the states a fit trains on;
* :mod:`~drlyap.training.warm_start` -- the LQR warm start;
* :mod:`~drlyap.training.acceptance` -- the acceptance check every run ends with, and the pair a fit keeps;
* :mod:`~drlyap.training.trainer` -- :func:`fit`: training alone;
* :mod:`~drlyap.training.certified` -- :func:`train`: training with counterexample-guided proof rounds, the
  default (``drlyap.train``).
"""

from drlyap.config import TrainConfig
from drlyap.sections import TrainSections
from drlyap.training.certified import train, train_cegis
from drlyap.training.trainer import TrainResult, fit

__all__ = ["TrainConfig", "TrainResult", "TrainSections", "fit", "train", "train_cegis"]
