"""Bring your own pair (``drlyap import``): a controller, and optionally a Lyapunov function V, from ONNX files for a
system, held as graphs (:mod:`drlyap.graph`: data, run by an interpreter that also runs on enclosures), so that it
gets the same proofs as a drlyap pair; and the closed loop of any controller that comes without a certificate
(an imported one, an RL actor: :func:`rl_actor_graph`) with the quadratic V of its linearisation.

* :func:`load_onnx_pair` -- ``(system, controller.onnx, lyapunov.onnx or None) -> ClosedLoop``;
* :func:`import_pair` -- the same with what was checked and how the files were read (:class:`ImportedPair`);
* :func:`quadratic_loop` -- V = ``z^T P z`` of the closed loop's linearisation at x* on the true model at nominal
  parameters, ``A^T P + P A = -S^-2`` (the Lyapunov equation with ``Q = I`` in box-scaled coordinates ``z = S y``,
  :func:`~drlyap.verification.linearisation.lyapunov_matrix`); refused where ``A`` is not Hurwitz or
  ``pi(x*) != u*`` beyond :data:`EQUILIBRIUM_TOL` (x* is then not an equilibrium);
* :func:`save_imported_run`, :func:`import_run`, :func:`load_imported_run` -- run directories of kind ``imported``.

Layout (written atomically; loading reads data only)::

    RUN_DIR/
      run.json       {"kind": "imported", "format": 2, "system": system.describe(), "system_source": ...}
      config.json    the system, the files read (name, sha256), the certificate's kind, the decay to prove, and the
                     level and delta of a drlyap export's claim
      graphs.json    the controller's and V's operations (Graph.to_json), or V's kind ("quadratic")
      tensors.pt     their constants, and P of a quadratic V (tensors only, read with weights_only=True)
      metrics.json   the checks at x* and notes on how the files were read
      source/        the ONNX files as given (for the record: never read when loading)
      figures/
"""

from __future__ import annotations

import hashlib
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor, nn

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import TrueDecrease, decay_at_shift
from drlyap.graph import INPUT, Graph, GraphBuilder, read_onnx, simplify
from drlyap.io import write_bytes_of, write_json
from drlyap.networks import QuadraticLyapunov, origin_like
from drlyap.runs.directory import RunDirError, atomic_dir, read_run_json, run_record, run_system
from drlyap.runs.policies import PolicyRun
from drlyap.runs.publish import check_writable
from drlyap.runs.validate import load_weights, restore_infinite
from drlyap.systems import UncertainSystem, resolve_system, system_source
from drlyap.verification.linearisation import is_hurwitz, lyapunov_matrix

F64 = torch.float64
EQUILIBRIUM_TOL = 1e-6
"""How far ``pi(x*)`` may be from u*, relative to U's half-widths (a float32 model's u* is rounded: the quadrotor's
hover thrust by 4e-8 of it); beyond it x* is not an equilibrium of the closed loop and nothing is imported."""
MINIMUM_TOL = 1e-9
"""How large ``|grad V(x*)| s`` may be relative to V's largest sampled value (``s``: the box's half-widths)."""


@dataclass
class ImportedPair:
    """A closed loop from graphs, with ``certificate`` (``onnx`` or ``quadratic``), the decay its decrease is proved
    with (``decay_rate`` gamma of ``gamma ||z||``, ``exp_rate`` alpha of ``alpha V``), the ``checks`` at x* and
    ``notes`` on how each file was read. ``level``, ``delta``: those of the run a drlyap export came from (its
    decrease is proved on ``{V <= level}`` minus the delta-ball, as the run's is; None: the whole region, the
    system's delta). ``pinned``: V is least at x* and pinned there (:class:`PinnedLyapunov`); False: V as given,
    whose claim can only be a band's (``verify --band``: convergence to a sublevel set, not to x*)."""

    loop: ClosedLoop
    certificate: str
    decay_rate: float
    exp_rate: float
    checks: dict = field(default_factory=dict)
    notes: dict = field(default_factory=dict)
    level: float | None = None
    delta: float | None = None
    pinned: bool = True

    @property
    def given_loop(self) -> ClosedLoop:
        """The closed loop with V as the file gives it (not pinned at x*): what a band claim is about, its levels in
        the V's own units."""
        lyapunov = self.loop.lyapunov
        if isinstance(lyapunov, PinnedLyapunov):
            return ClosedLoop(self.loop.system, lyapunov.graph, self.loop.controller)
        return self.loop

    def true_condition(self, xi: Tensor, exp_rate: float | None = None) -> TrueDecrease:
        """Decrease on the true model at the shifts ``xi (1, k)`` with the pair's decay, or with the decay ``exp_rate``
        (``alpha V`` alone) in place of its own."""
        return TrueDecrease(xi, *decay_at_shift(self.decay_rate, self.exp_rate, exp_rate))


def _claim_number(value, what: str, lowest: float, above: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and (
        value > lowest if above else value >= lowest)
    if not ok:
        raise ValueError(f"{what} must be a finite number {'>' if above else '>='} {lowest:g}, got {value!r}")
    return float(value)


def claim_of(record: dict) -> dict:
    """The claim of a drlyap export's record (``export.json``'s ``claim``): ``decay_rate``, ``exp_rate`` (>= 0),
    ``level`` (> 0, or None) and ``delta`` (>= 0), checked; a ValueError of one line otherwise."""
    claim = record.get("claim")
    if not isinstance(claim, dict):
        raise ValueError("the record has no 'claim' object")
    out = {name: _claim_number(claim.get(name), name, 0.0) for name in ("decay_rate", "exp_rate", "delta")}
    out["level"] = None if claim.get("level") is None else _claim_number(claim.get("level"), "level", 0.0, above=True)
    return out


def exported_claim(path: str | os.PathLike, system: UncertainSystem) -> dict | None:
    """The claim (:func:`claim_of`) that drlyap's export of a run keeps in an ONNX file's metadata (key ``drlyap``,
    ``export.json``'s record), or None for a file without it or one exported for another system. Read as data (JSON);
    a record that is there but damaged is refused with a ValueError of one line naming the file."""
    import json

    import onnx

    try:
        model = onnx.load(str(path), load_external_data=False)
    except Exception:  # read_onnx has read it already: it says what is wrong with it
        return None
    text = next((p.value for p in model.metadata_props if p.key == "drlyap"), None)
    if text is None:
        return None
    try:
        record = json.loads(text)
        name = record.get("system", {}).get("name")
    except (ValueError, AttributeError):
        raise ValueError(f"{path}: its drlyap record is not a JSON object") from None
    if name != system.name or "claim" not in record:  # another system's, or an export from before claims
        return None
    try:
        return claim_of(record)
    except ValueError as err:
        raise ValueError(f"{path}: its drlyap record's claim is damaged ({err})") from None


class PinnedLyapunov(nn.Module):
    """A graph V less its first-order part at x*: ``V(z) - V(0) - grad V(0) . z``, with ``V(0)`` and ``grad V(0)``
    computed by the graph itself at the origin (enclosed, where ``z`` is an enclosure). So ``V(x*) = 0`` and
    ``grad V(x*) = 0`` hold exactly in real arithmetic whatever the weights are, as the second-order proof near x*
    needs (:mod:`drlyap.verification.roa.local`). The import takes only graphs with ``|grad V(0)| s`` below
    :data:`MINIMUM_TOL` of V's range (``s``: the box's half-widths), so the linear term moves V by no more than that;
    a V whose float gradient at x* is 0 (an exported drlyap V) evaluates to the same floats."""

    def __init__(self, graph: Graph) -> None:
        super().__init__()
        self.graph = graph

    def forward(self, z):
        v0, g0 = self.graph.value_and_grad(origin_like(z))
        return self.graph(z) - v0 - (g0 * z).sum(-1)

    def value_and_grad(self, z):
        value, grad = self.graph.value_and_grad(z)
        v0, g0 = self.graph.value_and_grad(origin_like(z))
        return value - v0 - (g0 * z).sum(-1), grad - g0


# ----------------------------------------------------------------------------------------------- checks at x*
def _half_widths(system: UncertainSystem) -> Tensor:
    lo, hi = system.local_box()
    return (hi - lo) / 2


def equilibrium_offset(system: UncertainSystem, controller: nn.Module, what: str = "the controller") -> list[float]:
    """``pi(x*) - u*`` ``(m,)``; a ValueError where it exceeds :data:`EQUILIBRIUM_TOL` of U's half-widths."""
    with torch.no_grad():
        u = controller(torch.zeros(1, system.n, dtype=F64))[0]
    u_star = torch.tensor(system.equilibrium_input, dtype=F64)
    lo, hi = (torch.tensor(b, dtype=F64) for b in system.input_box)
    offset = u - u_star
    if not bool(torch.isfinite(offset).all()) or bool((offset.abs() > EQUILIBRIUM_TOL * (hi - lo) / 2).any()):
        raise ValueError(f"x* is not an equilibrium of {what}: pi(x*) - u* = "
                         f"{[float(f'{v:.6g}') for v in offset.tolist()]} (more than {EQUILIBRIUM_TOL:g} of U's "
                         "half-width)")
    return offset.tolist()


def pinned_certificate(system: UncertainSystem, graph: Graph, samples: int = 4096) -> tuple[nn.Module, dict]:
    """V with its minimum at x*: ``grad V(x*)`` must vanish (:data:`MINIMUM_TOL`) and no sampled state of the box
    may have ``V < V(x*)`` (else a ValueError); V is then pinned there to first order (:class:`PinnedLyapunov`)."""
    lo, hi = system.local_box()
    gen = torch.Generator().manual_seed(0)
    z = lo + (hi - lo) * torch.rand(samples, system.n, generator=gen, dtype=F64)
    with torch.no_grad():
        v0, g0 = graph.value_and_grad(torch.zeros(1, system.n, dtype=F64))
        values = graph(z)
    top = float(values.abs().max())
    slope = float((g0[0].abs() * _half_widths(system)).max())
    if not math.isfinite(slope) or slope > MINIMUM_TOL * max(top, 1e-300):
        raise ValueError(f"x* is not a minimum of V: grad V(x*) = {[float(f'{v:.6g}') for v in g0[0].tolist()]}")
    low = int(values.argmin())
    if float(values[low]) < float(v0[0]):
        x = system.to_user(z[low:low + 1])[0].tolist()
        raise ValueError(f"x* is not V's minimum: V = {float(values[low]):.6g} < V(x*) = {float(v0[0]):.6g} at "
                         f"x = {[float(f'{v:.6g}') for v in x]}")
    checks = {"V_at_equilibrium": float(v0[0]), "grad_V_at_equilibrium": g0[0].tolist()}
    return PinnedLyapunov(graph), checks


def quadratic_loop(system: UncertainSystem, controller: nn.Module, what: str = "the controller") -> tuple[ClosedLoop, dict]:
    """The closed loop with ``V = z^T P z`` of its linearisation (module docstring) and the checks made: ``A``, its
    eigenvalues, ``P``, and ``exp_rate``: half the decay rate ``z^T P z`` has along the linearisation
    (``1 / lambda_max(S P S)``), the scale-free decay its decrease is proved with, as for LQR."""
    offset = equilibrium_offset(system, controller, what)
    loop = ClosedLoop(system, None, controller)
    _, jac = loop.jacobian(torch.zeros(1, system.n, dtype=F64))
    a = jac[0]
    hurwitz, eigenvalues = is_hurwitz(a)
    shown = [f"{v.real:.4g}{v.imag:+.4g}j" for v in eigenvalues]
    if not hurwitz:
        raise ValueError(f"the closed loop's linearisation at x* is not Hurwitz (eigenvalues {', '.join(shown)}): "
                         "no quadratic Lyapunov function")
    s = _half_widths(system)
    p = lyapunov_matrix(a, s)
    rate = 1.0 / float(torch.linalg.eigvalsh(s[:, None] * p * s[None, :]).max())
    checks = {"pi_minus_u_star": offset, "A": a.tolist(), "eigenvalues": [[v.real, v.imag] for v in eigenvalues],
              "P": p.tolist(), "exp_rate": 0.5 * rate}
    return ClosedLoop(system, QuadraticLyapunov(p), controller), checks


# ----------------------------------------------------------------------------------------------- from files
def import_pair(system: UncertainSystem, controller_path: str | os.PathLike,
                lyapunov_path: str | os.PathLike | None = None) -> ImportedPair:
    """Read a controller (and V) of ``system`` from ONNX files (:func:`drlyap.graph.read_onnx`) and check them at
    x*: ``pi(x*) = u*``, and V's minimum at x* (:func:`pinned_certificate`), or without V the quadratic V of the
    linearisation (:func:`quadratic_loop`). Every refusal is a ValueError of one line."""
    controller, notes = read_onnx(controller_path, system, "controller")
    all_notes = {"controller": notes}
    if lyapunov_path is None:
        loop, checks = quadratic_loop(system, controller)
        return ImportedPair(loop, "quadratic", 0.0, checks["exp_rate"], checks, all_notes)
    graph, all_notes["lyapunov"] = read_onnx(lyapunov_path, system, "lyapunov")
    offset = equilibrium_offset(system, controller)
    pinned = True
    try:
        lyapunov, checks = pinned_certificate(system, graph)
    except ValueError as err:  # a V not least at x* (the field's sigmoid V): taken as given, for a band claim
        pinned, lyapunov = False, graph
        with torch.no_grad():
            v0, g0 = graph.value_and_grad(torch.zeros(1, system.n, dtype=F64))
        checks = {"V_at_equilibrium": float(v0[0]), "grad_V_at_equilibrium": g0[0].tolist()}
        all_notes["lyapunov"].append(f"{err}: V is taken as given, not pinned at x*; what it can claim is decrease on "
                                     "a band C1 <= V <= C2 (`drlyap verify RUN --band C1,C2`), convergence to "
                                     "{V <= C1}, not to x*")
    checks["pi_minus_u_star"] = offset
    claim = exported_claim(lyapunov_path, system)
    if claim is None:  # plain decrease on the whole region: a decay with gamma ||z|| would depend on V's scale
        claim = {"decay_rate": 0.0, "exp_rate": 0.0, "level": None, "delta": None}
        all_notes["lyapunov"].append("not a drlyap export: plain decrease Vdot <= 0 is its claim (at a shift a region "
                                     "asks Vdot + 0.01 V <= 0, which no scale of V changes)")
    else:
        where = "the whole region" if claim["level"] is None else f"{{V <= {claim['level']:.6g}}}"
        all_notes["lyapunov"].append(f"a drlyap export: its run's claim is taken (decrease with gamma = "
                                     f"{claim['decay_rate']:g}, alpha = {claim['exp_rate']:g} on {where} minus the "
                                     f"ball of radius {claim['delta']:g})")
    return ImportedPair(ClosedLoop(system, lyapunov, controller), "onnx", claim["decay_rate"], claim["exp_rate"],
                        checks, all_notes, claim["level"], claim["delta"], pinned)


def load_onnx_pair(system: UncertainSystem, controller_path: str | os.PathLike,
                   lyapunov_path: str | os.PathLike | None = None) -> ClosedLoop:
    """The closed loop ``(system, V, pi)`` of a controller and V (None: the quadratic V of the linearisation) read
    from ONNX files (:func:`import_pair`)."""
    return import_pair(system, controller_path, lyapunov_path).loop


# ----------------------------------------------------------------------------------------------- RL actors
def rl_actor_graph(system: UncertainSystem, algo: str, policy: nn.Module) -> Graph:
    """The deterministic action of a stable-baselines3 policy (SAC: ``low + (tanh(mu(latent)) + 1) / 2 (high - low)``;
    PPO: the action net's mean, clamped to U), as a graph on local states, read from the policy's own layers.

    The agent sees the wrapped state clipped to X; on the local box both are the identity (the box's angle sides
    lie in ``[-pi, pi]``), so the graph reads ``x* + z``, as :mod:`drlyap.graph.from_onnx` argues for a wrap."""
    if algo == "sac":
        body, head, squash = policy.actor.latent_pi, policy.actor.mu, True
    elif algo == "ppo":
        if getattr(policy, "squash_output", False):
            raise ValueError("a PPO policy with squashed outputs is not read")
        body, head, squash = policy.mlp_extractor.policy_net, policy.action_net, False
    else:
        raise ValueError(f"unknown algorithm {algo!r}; valid: sac, ppo")
    b = GraphBuilder(system.n, f"{algo} actor")
    x_star = torch.tensor(system.equilibrium, dtype=F64)
    h = b.emit("add", [INPUT, b.constant(x_star, "x_star")]) if bool(x_star.any()) else INPUT
    layers = [*body, *(head if isinstance(head, nn.Sequential) else [head])]  # SAC with gSDE: Linear, Hardtanh
    for layer in layers:
        if isinstance(layer, nn.Linear):
            args = [h, b.constant(layer.weight)] + ([] if layer.bias is None else [b.constant(layer.bias)])
            h = b.emit("linear", args)
        elif isinstance(layer, nn.ReLU):
            h = b.emit("clamp", [h, b.constant(torch.tensor(0.0)), b.constant(torch.tensor(math.inf))])
        elif isinstance(layer, nn.Tanh):
            h = b.emit("tanh", [h])
        elif isinstance(layer, nn.Hardtanh):
            bounds = [b.constant(torch.tensor(float(v))) for v in (layer.min_val, layer.max_val)]
            h = b.emit("clamp", [h, *bounds])
        else:
            raise ValueError(f"the {algo} actor's layer {type(layer).__name__} is not read (Linear, ReLU, Tanh, "
                             "Hardtanh are)")
    if squash:
        lo, hi = (torch.tensor(v, dtype=F64) for v in system.input_box)
        h = b.emit("mul", [b.constant(torch.tensor(0.5)), b.emit("add", [b.emit("tanh", [h]), b.constant(torch.tensor(1.0))])])
        h = b.emit("add", [b.constant(lo, "u_low"), b.emit("mul", [h, b.constant(hi - lo, "u_width")])])
    nodes, constants, output, _ = simplify(b.nodes, b.constants, h, tuple(list(v) for v in system.input_box))
    return Graph(nodes, constants, output, system.n, f"{algo} actor")


# ----------------------------------------------------------------------------------------------- run directories
def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(2**20), b""):
            digest.update(block)
    return digest.hexdigest()


def _pack(tensors: dict[str, Tensor]) -> dict[str, Tensor]:
    """Constants with the infinite bounds of one-sided clamps as an int8 sign beside them (a weights file holds
    finite numbers only)."""
    out = {}
    for name, t in tensors.items():
        inf = torch.isinf(t)
        out[name] = torch.where(inf, 0.0, t)
        if bool(inf.any()):
            out[f"{name}#inf"] = torch.sign(t).to(torch.int8) * inf.to(torch.int8)
    return out


def save_imported_run(out: str | os.PathLike, pair: ImportedPair, files: dict[str, Path],
                      source: dict | None = None) -> Path:
    """Write an imported pair as a run directory of kind ``imported`` (atomically); ``files``: role -> the ONNX file
    read (copied into ``source/`` with its sha256 in ``config.json``)."""
    system, loop = pair.loop.system, pair.loop
    graphs = {"controller": loop.controller.to_json()}
    tensors = {"controller": _pack(loop.controller.tensors())}
    if pair.certificate == "quadratic":
        graphs["lyapunov"] = {"kind": "quadratic"}
        tensors["lyapunov"] = {"P": loop.lyapunov.P.detach().clone()}
    else:
        graph = loop.lyapunov.graph if isinstance(loop.lyapunov, PinnedLyapunov) else loop.lyapunov
        graphs["lyapunov"] = {"kind": "graph", "pinned": "first order" if pair.pinned else "no"} | graph.to_json()
        tensors["lyapunov"] = _pack(graph.tensors())
    config = {"system": system.name, "certificate": pair.certificate, "decay_rate": pair.decay_rate,
              "exp_rate": pair.exp_rate, "level": pair.level, "delta": pair.delta,
              "files": {role: {"name": Path(p).name, "sha256": _sha256(p)} for role, p in files.items()}}

    def fill(tmp: Path) -> None:
        write_json(tmp / "config.json", config)
        write_json(tmp / "graphs.json", graphs)
        write_bytes_of(tmp / "tensors.pt", lambda buffer: torch.save(tensors, buffer))
        write_json(tmp / "metrics.json", {"samples": None, "train_time_s": None, "checks": pair.checks,
                                          "notes": pair.notes})
        (tmp / "source").mkdir()
        for role, p in files.items():
            shutil.copyfile(p, tmp / "source" / f"{role}.onnx")
        (tmp / "figures").mkdir()
        write_json(tmp / "run.json", run_record("imported", system, source))

    return atomic_dir(Path(out), fill)


def import_run(system: str | UncertainSystem, controller: str | os.PathLike, out: str | os.PathLike,
               lyapunov: str | os.PathLike | None = None) -> ImportedPair:
    """``drlyap import``: read the files (:func:`import_pair`) and write the run directory ``out``."""
    source = None
    if isinstance(system, str):
        spec, system = system, resolve_system(system)
        source = system_source(spec, system)
    check_writable(out)
    pair = import_pair(system, controller, lyapunov)
    files = {"controller": Path(controller)} | ({} if lyapunov is None else {"lyapunov": Path(lyapunov)})
    save_imported_run(out, pair, files, source)
    return pair


def load_imported_run(path: str | os.PathLike, system: UncertainSystem | None = None, trust: bool = False) -> PolicyRun:
    """An imported run directory as a :class:`~drlyap.runs.PolicyRun` (``system``, ``trust``: as
    :func:`drlyap.runs.load_run`); ``info["pair"]`` is its :class:`ImportedPair`."""
    path = Path(path)
    info, config, graphs, metrics = read_run_json(path, "imported", "run.json", "config.json", "graphs.json",
                                                  "metrics.json")
    if not isinstance(config.get("system"), str) or config.get("certificate") not in ("onnx", "quadratic"):
        raise RunDirError(f"{path / 'config.json'}: an imported run's config needs 'system' and 'certificate' "
                          "(onnx or quadratic)")
    system = run_system(path, config["system"], system, info, trust)
    tensors = load_weights(path / "tensors.pt")
    try:
        controller = Graph.from_json(graphs["controller"], restore_infinite(tensors["controller"]), f"{path}: controller")
        spec = graphs["lyapunov"]
        pinned = spec.get("kind") == "quadratic" or spec.get("pinned") != "no"  # else a V as given (not least at x*)
        if spec.get("kind") == "quadratic":
            p = tensors["lyapunov"]["P"].to(F64)
            if p.shape != (system.n, system.n):
                raise ValueError(f"P has shape {tuple(p.shape)}, not ({system.n}, {system.n})")
            lyapunov: nn.Module = QuadraticLyapunov(p)
        else:
            graph = Graph.from_json(spec, restore_infinite(tensors["lyapunov"]), f"{path}: lyapunov")
            lyapunov = PinnedLyapunov(graph) if pinned else graph  # a V least at x* is pinned there to first order
        if controller.n != system.n or controller.out_shape != (system.m,):
            raise ValueError(f"the controller maps {controller.n} states to {controller.out_shape}, not "
                             f"{system.n} to ({system.m},)")
        if spec.get("kind") != "quadratic":
            if graph.n != system.n or graph.out_shape != ():
                raise ValueError(f"V maps {graph.n} states to {graph.out_shape}, not {system.n} to ()")
        decay, exp_rate = float(config.get("decay_rate", 0.0)), float(config.get("exp_rate", 0.0))
        level = None if config.get("level") is None else _claim_number(config["level"], "level", 0.0, above=True)
        delta = None if config.get("delta") is None else _claim_number(config["delta"], "delta", 0.0)
    except (KeyError, TypeError, ValueError) as err:
        raise RunDirError(f"{path}: graphs.json/tensors.pt do not describe a pair of {system.name} ({err})") from None
    loop = ClosedLoop(system, lyapunov, controller)
    pair = ImportedPair(loop, config["certificate"], decay, exp_rate, metrics.get("checks", {}), metrics.get("notes", {}),
                        level, delta, pinned)

    @torch.no_grad()
    def act(x: Tensor) -> Tensor:
        return controller(system.to_local(_states(system, x)))

    @torch.no_grad()
    def value(x: Tensor) -> Tensor:
        return lyapunov(system.to_local(_states(system, x)))

    return PolicyRun(path, "imported", system, act, value, None, None, f"imported-{config['certificate']}", config,
                     metrics, {"pair": pair, "loop": loop})


def _states(system: UncertainSystem, x) -> Tensor:
    x = torch.as_tensor(x)
    if x.ndim != 2 or x.shape[1] != system.n:
        raise ValueError(f"{system.name} states must have shape (B, {system.n}), got {tuple(x.shape)}")
    return x.to(F64)
