"""Fits kept beside a proof's checkpoints, so that an interrupted ``drlyap train`` run again does not train again what
it already trained: each round's fit is saved (sealed, as a proof's checkpoint: :mod:`drlyap.verification.checkpoints`)
under the sha256 of everything it depends on (the resolved config, the system, the pair it started from, the extra
states and open boxes it trained on, what it trained), with the generator state it left; a rerun of the same round
loads it instead of fitting (training is deterministic, so the pair is the one the fit would give) and says so."""

from __future__ import annotations

import copy
import hashlib
import json
import sys
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.config import TrainConfig
from drlyap.io import jsonable
from drlyap.networks import Controller, Lyapunov
from drlyap.sections import TrainSections
from drlyap.systems import UncertainSystem
from drlyap.training.boxes import OpenBoxes
from drlyap.training.trainer import TrainResult, fit
from drlyap.verification.checkpoints import load_checkpoint, save_checkpoint, update_hash


def _update(h, t: Tensor | None) -> None:
    if t is None:
        h.update(b"none")
    else:
        update_hash(h, t)


@dataclass(frozen=True)
class FitStart:
    """What a fit starts from and trains on beside its config (:func:`~drlyap.training.trainer.fit`'s keywords): the
    pair ``init`` (None: fresh networks), the local ``extra_states`` ``(E, n)`` added to every batch, whether the
    growth term acts (``grow``), the open ``boxes`` whose verifier bound is trained on, and whether V is trained
    (``train_lyapunov``)."""

    init: tuple[Lyapunov, Controller] | None = None
    extra_states: Tensor | None = None
    grow: bool = True
    boxes: OpenBoxes | None = None
    train_lyapunov: bool = True


def fit_key(cfg: TrainConfig, system: UncertainSystem, start: FitStart) -> str:
    """The sha256 (hex) of what a fit depends on."""
    boxes = start.boxes
    h = hashlib.sha256(b"drlyap-fit/1")
    h.update(json.dumps(cfg.to_dict(), sort_keys=True, default=str).encode())
    h.update(json.dumps(system.describe(), sort_keys=True, default=str).encode())
    for net in start.init or ():
        for name, value in sorted(net.state_dict().items()):
            h.update(name.encode())
            _update(h, value)
    _update(h, start.extra_states)
    _update(h, None if boxes is None else boxes.lo)
    _update(h, None if boxes is None else boxes.hi)
    h.update(json.dumps([start.grow, start.train_lyapunov, None if boxes is None else [
        boxes.level, str(boxes.enclosure), boxes.weight, boxes.margin, boxes.batch]], default=str).encode())
    return h.hexdigest()


def fit_or_resume(folder: str | None, cfg: TrainConfig, system: UncertainSystem, start: FitStart,
                  progress: bool) -> TrainResult:
    """:func:`~drlyap.training.trainer.fit` from ``start``, or, where ``folder`` keeps a sealed fit of the very same
    arguments, that fit (and torch's generator state as the fit left it); a new fit is kept in ``folder``."""
    key = None if folder is None else fit_key(cfg, system, start)
    saved = None if key is None else load_checkpoint(folder, key)
    if saved is not None:  # the pair and the xi samples kept, torch's generator state as the fit left it
        arrays, header = saved
        plan = TrainSections.of(cfg)
        lyapunov, controller = (copy.deepcopy(n) for n in start.init) if start.init else plan.networks.build(system)
        lyapunov.load_state_dict({k.removeprefix("lyapunov."): v for k, v in arrays.items()
                                  if k.startswith("lyapunov.")})
        controller.load_state_dict({k.removeprefix("controller."): v for k, v in arrays.items()
                                    if k.startswith("controller.")})
        xi_all = arrays["xi_all"]
        condition = plan.condition.build(plan.condition.training_samples(xi_all))
        torch.set_rng_state(arrays["rng"].to(torch.uint8))
        if progress:
            print(f"{cfg.system} {cfg.method}: this training was done before an interruption; its pair is taken "
                  "from the checkpoint, not trained again", file=sys.stderr, flush=True)
        return TrainResult(cfg, system, lyapunov, controller, xi_all, condition, header["history"], header["metrics"])
    result = fit(cfg, system, progress=progress, init=start.init, extra_states=start.extra_states, grow=start.grow,
                 boxes=start.boxes, train_lyapunov=start.train_lyapunov)
    if key is None:
        return result
    arrays = {f"lyapunov.{k}": v for k, v in result.lyapunov.state_dict().items()}
    arrays |= {f"controller.{k}": v for k, v in result.controller.state_dict().items()}
    arrays |= {"xi_all": result.xi_samples, "rng": torch.get_rng_state()}
    try:
        save_checkpoint(folder, key, arrays, {"history": result.history, "metrics": jsonable(result.metrics)})
    except OSError:  # no place to keep it: the fit is done again after an interruption
        pass
    return result

