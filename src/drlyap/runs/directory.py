"""Run directories of trained pairs: the unit every command reads and writes (docs/run-directory.md).

Layout (all written into a temporary sibling and renamed into place at the end, so an interrupted
or failed run never leaves a directory that looks complete)::

    RUN_DIR/
      run.json        kind, format, system description and source (marks the directory complete)
      config.json     the exact TrainConfig the run used
      weights.pt      state dicts of the certificate and the controller (tensors only)
      metrics.json    acceptance check, training summary, xi samples, proofs, later evaluations
      history.csv     iteration, loss, seconds
      figures/        PNG figures written by commands that plot

Loading a run reads data only: its files are validated (:mod:`drlyap.runs.validate`), its weights are read as
tensors, and a system that came from a file or a module is rebuilt only from code the caller names (``system=``)
or explicitly trusts (``trust=True``), never from what the run directory says to import.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, decay_at_shift
from drlyap.config import TrainConfig
from drlyap.io import write_json, write_json_atomic
from drlyap.networks import Controller, Lyapunov
from drlyap.proof_settings import ProofConfig, legacy_proof
from drlyap.records import AcceptanceCheck, TrainingRecord
from drlyap.regions import Region
from drlyap.runs.certificates import PairFiles, Stated, write_certificate
from drlyap.runs.publish import RunDirError, atomic_dir, ensure_new
from drlyap.runs.reading import read_run_json, read_run_kind, run_system
from drlyap.runs.validate import check_config, check_samples, check_schema, load_weights
from drlyap.sections import TrainSections
from drlyap.systems import UncertainSystem, default_source
from drlyap.verification import Certificate

if TYPE_CHECKING:
    from drlyap.training import TrainResult

FORMAT_VERSION = 2
"""2: proof settings in metrics.json (``proof``); runs of format 1 load too."""

__all__ = ["FORMAT_VERSION", "Run", "RunDirError", "atomic_dir", "ensure_new", "load_run", "read_run_json",
           "read_run_kind", "run_record", "run_system", "save_run"]


def run_record(kind: str, system: UncertainSystem, source: dict | None = None) -> dict:
    """The ``run.json`` of a run of ``kind``: format, ``system.describe()`` and where the system came from
    (``source``: :func:`drlyap.systems.system_source`; default :func:`drlyap.systems.default_source`)."""
    return {"kind": kind, "format": FORMAT_VERSION, "system": system.describe(),
            "system_source": source if source is not None else default_source(system)}


def save_run(out: Path, result: TrainResult, overwrite: bool = False,
             extra: Callable[[Path], None] | None = None, source: dict | None = None) -> Path:
    """Write a trained pair as a run directory at ``out`` (atomically); ``extra(tmp)`` may add files.

    ``source`` records where the system came from (see :func:`run_record`) so that commands reload it.
    """

    def fill(tmp: Path) -> None:
        write_json(tmp / "config.json", result.config.to_dict())
        torch.save({"lyapunov": result.lyapunov.state_dict(), "controller": result.controller.state_dict()},
                   tmp / "weights.pt")
        proof = result.trained_proof
        if proof is not None and proof.partition is not None:
            write_certificate(tmp, "trained", proof,
                              Stated(result.condition, Region.of(result.system, float(result.config.delta))),
                              result.system, PairFiles.networks(tmp, result.config.alpha_hat))
        write_json(tmp / "metrics.json", result.metrics)
        with open(tmp / "history.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=["iteration", "loss", "time_s"])
            writer.writeheader()
            writer.writerows(result.history)
        (tmp / "figures").mkdir()
        if extra is not None:
            extra(tmp)
        write_json(tmp / "run.json", run_record("lyapunov", result.system, source))

    return atomic_dir(out, fill, overwrite)


@dataclass
class Run:
    """A loaded run: the system, the networks and the record. Callables take user coordinates.

    ``run.controller(x)`` maps states ``x (B, n)`` (user coordinates, angles in any branch) to inputs
    ``(B, m)``; ``run.lyapunov(x)`` to certificate values ``(B,)``. Both accept any float tensor and
    return float64.
    """

    path: Path
    system: UncertainSystem
    config: TrainConfig
    metrics: dict
    lyapunov_net: Lyapunov
    controller_net: Controller
    proof: ProofConfig | None = None

    @cached_property
    def sections(self) -> TrainSections:
        """The run's config in sections (:class:`~drlyap.sections.TrainSections`)."""
        return TrainSections.of(self.config)

    @cached_property
    def loop(self) -> ClosedLoop:
        """The run's closed loop (system, V, pi), what every proof of it is about."""
        return ClosedLoop(self.system, self.lyapunov_net, self.controller_net)

    @property
    def condition(self) -> Condition:
        """The condition the run was trained on (:meth:`~drlyap.sections.ConditionSection.build`)."""
        return self.sections.condition.build(self.xi_train)

    def region_condition(self, xi=None, exp_rate: float | None = None) -> Condition | None:
        """The per-state condition a region of attraction of the run rests on: its trained condition, or with a shift
        ``xi (k,)`` decrease on the true model there (``exp_rate``: its decay ``alpha V``, None: the run's); for the DR
        uniform condition (one inequality, no per-state residual) the decrease at every sample it implies
        (:meth:`~drlyap.conditions.Condition.per_sample`, None where it implies none)."""
        condition = self.condition if xi is None else self.true_condition(xi, exp_rate)
        return condition if condition.per_state else condition.per_sample(condition.decay_rate, condition.exp_rate)

    def true_condition(self, xi, exp_rate: float | None = None) -> Condition:
        """Plain decrease on the true model at the shift ``xi (k,)``, with the run's decay terms (``exp_rate``: the decay
        ``alpha V`` alone in their place, ``Vdot + alpha V <= 0``)."""
        section = self.sections.condition
        gamma, alpha = decay_at_shift(section.decay_rate, section.exp_rate, exp_rate)
        return replace(section, decay_rate=gamma, exp_rate=alpha).build(self.system.check_xi(xi)[None], "true")

    @property
    def acceptance(self) -> AcceptanceCheck | None:
        """The acceptance check of the run's pair (``metrics["acceptance"]``), or None where the run has none."""
        data = self.metrics.get("acceptance")
        return AcceptanceCheck.from_dict(data) if isinstance(data, dict) else None

    @property
    def record(self) -> TrainingRecord | None:
        """What the run's training recorded (:class:`~drlyap.records.TrainingRecord`), or None where the run was not
        trained by drlyap's trainer (e.g. an RL baseline)."""
        return TrainingRecord.from_metrics(self.metrics) if TrainingRecord.readable(self.metrics) else None

    @property
    def certificate(self) -> Certificate | None:
        """What was proved about the run's trained condition (``metrics["certificate"]``), or None."""
        cert = self.metrics.get("certificate")
        return Certificate.from_dict(cert) if isinstance(cert, dict) and "status" in cert else None

    @property
    def xi_samples(self) -> Tensor:
        """The training samples of xi, ``(N, k)``."""
        return torch.as_tensor(self.metrics["xi_samples"], dtype=torch.float64)

    @property
    def xi_train(self) -> Tensor:
        """The samples the condition used: all of them for DR, their mean for the baseline."""
        return torch.as_tensor(self.metrics["xi_train"], dtype=torch.float64)

    def _check(self, x: Tensor) -> Tensor:
        x = torch.as_tensor(x)
        if x.ndim != 2 or x.shape[1] != self.system.n:
            raise ValueError(f"{self.system.name} states must have shape (B, {self.system.n}), got {tuple(x.shape)}")
        return x.to(torch.float64)

    @torch.no_grad()
    def controller(self, x: Tensor) -> Tensor:
        z = self.system.to_local(self._check(x))
        return self.controller_net(z.float()).double()

    @torch.no_grad()
    def lyapunov(self, x: Tensor) -> Tensor:
        z = self.system.to_local(self._check(x))
        return self.lyapunov_net(z.float()).double()

    def save_metrics(self) -> None:
        """Rewrite ``metrics.json`` (atomically, via a temporary file)."""
        write_json_atomic(self.path / "metrics.json", self.metrics)

    def keep(self, entries: dict, *, certificate: bool = False) -> None:
        """Keep ``entries`` (names to JSON data) in the run's ``metrics.json`` (with ``certificate``: in its
        ``certificate`` entry, beside the verdict on the trained condition) and rewrite the file once; nothing is
        written where there is nothing to keep."""
        if not entries:
            return
        target = self.metrics
        if certificate:  # a run saved without a verdict (``fit`` then ``save_run``) gets "not checked" beside them
            target = self.metrics["certificate"] = self.metrics.get("certificate") or Certificate(
                status="not checked", condition=self.condition.label).to_dict()
        target.update(entries)
        self.save_metrics()


def load_run(path: str | os.PathLike, system: UncertainSystem | None = None, trust: bool = False) -> Run:
    """Load a Lyapunov run directory (its files validated, its weights read as tensors).

    ``system``: the system object, needed for a user-defined system that came from a file or a module (its name
    must match the one the run was trained on); ``trust``: rebuild such a system from the file or module the run
    records instead (that runs its code). A registered system needs neither.
    """
    path = Path(path)
    info, raw_config, metrics = read_run_json(path, "lyapunov", "run.json", "config.json", "metrics.json")
    config = check_config(path / "config.json", raw_config, int(info.get("format", 1)))
    check_schema(path / "metrics.json", metrics, "metrics")
    system = run_system(path, config.system, system, info, trust)
    if info["system"]["n"] != system.n or info["system"]["m"] != system.m:
        raise RunDirError(f"{path} has dimensions n={info['system']['n']}, m={info['system']['m']}; "
                          f"system {system.name} has n={system.n}, m={system.m}")
    try:
        config.validate(system)
    except ValueError as err:
        raise RunDirError(f"{path / 'config.json'}: {err}") from None
    check_samples(path / "metrics.json", metrics, system.k)
    weights = load_weights(path / "weights.pt")
    lyapunov, controller = TrainSections.of(config).networks.build(system)
    try:
        lyapunov.load_state_dict(weights["lyapunov"])
        controller.load_state_dict(weights["controller"])
    except (KeyError, RuntimeError) as err:
        raise RunDirError(f"{path}: weights.pt does not fit config.json ({str(err).splitlines()[0]})") from err
    lyapunov.eval()
    controller.eval()
    try:
        proof = ProofConfig.from_dict(metrics["proof"]) if isinstance(metrics.get("proof"), dict) else \
            legacy_proof(raw_config)
    except (TypeError, ValueError) as err:
        raise RunDirError(f"{path / 'metrics.json'}: proof: {err}") from None
    return Run(path, system, config, metrics, lyapunov, controller, proof)
