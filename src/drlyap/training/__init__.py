"""Training a controller and its certificate, and proving what was trained.

* :class:`TrainConfig` (:mod:`drlyap.config`, resolved once against its system) and what it builds
  (:mod:`drlyap.assembly`: the networks, :func:`run_condition`: a run's conditions);
* :mod:`~drlyap.training.acceptance` -- the acceptance check every run ends with;
* :mod:`~drlyap.training.trainer` -- :func:`fit`: training alone (with the LQR warm start);
* :mod:`~drlyap.training.certified` -- :func:`train`: training with counterexample-guided proof rounds, the
  default (``drlyap.train``).
"""

from drlyap.assembly import build_networks, draw_xi_samples, run_condition, training_region
from drlyap.config import TrainConfig
from drlyap.training.certified import certificate, train, train_cegis
from drlyap.training.trainer import TrainResult, fit

__all__ = ["TrainConfig", "TrainResult", "build_networks", "certificate", "draw_xi_samples", "fit", "run_condition",
           "train", "train_cegis", "training_region"]
