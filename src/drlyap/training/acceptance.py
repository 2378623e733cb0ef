"""The acceptance check every training run ends with (SPEC §5): cheap checks that a pair stabilises.

A near-zero training loss does not mean a stabilising pair: the authors' code reached one with a
controller that failed every test state. Three cheap checks separated good runs from bad ones:

1. the trained condition on a dense set of states *not used for training* (maximum violation and
   violating fraction over X_delta);
2. the closed-loop Jacobian at x* on the true model, Hurwitz for every xi sample and for their mean;
3. a batched Newton root search for other closed-loop equilibria in X_delta (where Vdot = 0, so the
   decrease condition must fail around them).

A run passes when the condition holds at every validation state, every Jacobian is Hurwitz and no
other equilibrium is found (for a pair trained for a set ``{V <= level}``, none in that set: an equilibrium
outside it, e.g. where a saturated input cannot hold the system, contradicts nothing the pair is trained for).
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition, DecreaseTerms, local_rates
from drlyap.networks import Controller, Lyapunov
from drlyap.records import AcceptanceCheck
from drlyap.regions import Region
from drlyap.training.states import TrainingStates, inside_states


def condition_residual(loop: ClosedLoop, condition: Condition, z: Tensor, chunk: int = 20000) -> Tensor:
    """The condition's residual at local states ``z (B, n)`` (in the networks' dtype), chunked, without gradients.

    For a uniform condition the Lipschitz term uses the maximum over *all* of ``z``.
    """
    ref = next(loop.lyapunov.parameters())
    with torch.no_grad():
        parts = [condition.terms(loop, z[i:i + chunk].to(ref)) for i in range(0, z.shape[0], chunk)]
    terms = DecreaseTerms(vdot=torch.cat([p.vdot for p in parts]),
                          lip=None if parts[0].lip is None else torch.cat([p.lip for p in parts]),
                          decay=torch.cat([p.decay for p in parts]))
    return condition.residual(terms)


def with_mean(xi_samples: Tensor) -> Tensor:
    """The samples ``(N, k)`` followed by their mean: ``(N + 1, k)``."""
    return torch.cat([xi_samples, xi_samples.mean(0, keepdim=True)])


def jacobian_check(loop: ClosedLoop, xi_samples: Tensor) -> dict:
    """Eigenvalues of the true closed-loop Jacobian at x* for each xi sample and their mean."""
    ref = next(loop.controller.parameters())
    xis = with_mean(xi_samples).to(ref)
    z = torch.zeros(xis.shape[0], loop.n, dtype=ref.dtype, device=ref.device)
    _, jac = loop.jacobian(z, xis)
    jac = jac.double().cpu()
    finite = torch.isfinite(jac).flatten(1).all(-1)
    max_real = torch.full((jac.shape[0],), float("nan"), dtype=torch.float64)
    if bool(finite.any()):  # a non-finite Jacobian (diverged networks) has no eigenvalues: reported as NaN
        max_real[finite] = torch.linalg.eigvals(jac[finite]).real.amax(-1)
    return {
        "max_real_eigenvalue": [float(v) for v in max_real],
        "hurwitz": bool((max_real < 0).all()),  # False where NaN
        "labels": [f"xi_{i}" for i in range(xi_samples.shape[0])] + ["mean"],
    }


def find_equilibria(loop: ClosedLoop, xi_samples: Tensor, delta: float, starts_per_axis: int = 24,
                    iterations: int = 40, seed: int = 0) -> list[dict]:
    """Other closed-loop equilibria in X_delta, by a damped Newton search from a grid of starts.

    Runs for every xi sample and the mean at once (batched over starts x samples). Returns one entry
    per distinct root: local state, user state, which xi, residual norm.
    """
    system = loop.system
    ref = next(loop.controller.parameters())
    dtype = ref.dtype
    lo, hi = (b.to(ref) for b in system.local_box())
    per = max(2, int(round(starts_per_axis ** (2 / max(system.n, 2)))) if system.n > 2 else starts_per_axis)
    axes = [lo[i] + (hi[i] - lo[i]) * (torch.arange(per, dtype=dtype, device=ref.device) + 0.5) / per
            for i in range(system.n)]
    starts = torch.cartesian_prod(*axes).reshape(-1, system.n)
    xis = with_mean(xi_samples).to(ref)
    s, q = starts.shape[0], xis.shape[0]
    z = starts.repeat(q, 1)
    xi = xis.repeat_interleave(s, dim=0)
    width = hi - lo
    with torch.no_grad():
        scale = loop.rhs(starts, xis[-1].expand(s, -1)).norm(dim=-1).median()
    for _ in range(iterations):
        f, jac = loop.jacobian(z, xi)
        # tiny n x n least-squares solves: on the CPU in float64 (CUDA's lstsq assumes full rank)
        jac, f = jac.double().cpu(), f.double().cpu()
        ok = torch.isfinite(jac).flatten(1).all(-1) & torch.isfinite(f).all(-1)
        jac = torch.where(ok[:, None, None], jac, torch.eye(system.n, dtype=jac.dtype))
        f = torch.where(ok[:, None], f, 0.0)  # a start where the loop is not finite stays put (and is not a root)
        step = torch.linalg.lstsq(jac, -f.unsqueeze(-1)).solution.squeeze(-1)
        step = torch.nan_to_num(step).to(z)
        limit = 0.1 * width
        step = torch.maximum(torch.minimum(step, limit), -limit)
        z = torch.minimum(torch.maximum(z + step, lo), hi)
    with torch.no_grad():
        f = loop.rhs(z, xi)
    residual = f.norm(dim=-1) / max(float(scale), 1e-300)
    keep = (residual < 1e-6) & (z.norm(dim=-1) >= delta)
    found: list[dict] = []
    index = (torch.arange(s * q, device=z.device) // s)[keep].cpu()
    for zi, qi, ri in zip(z[keep].cpu(), index, residual[keep].cpu()):
        if any(e["xi_index"] == int(qi) and torch.allclose(torch.tensor(e["local"], dtype=dtype), zi,
                                                            atol=1e-3 * float(width.max())) for e in found):
            continue
        found.append({"local": zi.tolist(), "state": system.to_user(zi[None])[0].tolist(), "xi_index": int(qi),
                      "xi_label": "mean" if qi == q - 1 else f"xi_{int(qi)}", "relative_residual": float(ri)})
    return found


@dataclass(frozen=True)
class SetAsked:
    """What the acceptance check asks of a pair trained for the sublevel set ``{V <= level}``: the condition only at
    the validation states with ``V <= level``, and V above ``level`` at every state of ``faces`` ``(F, n)`` (None:
    20,000 fixed states on the box's boundary), so that the set lies inside the box; with ``face_levels`` ``(F,)``,
    V above each face state's own level instead (``level`` is then compared with V's least value on the faces only in
    the record)."""

    level: float
    faces: Tensor | None = None
    face_levels: Tensor | None = None


def acceptance_check(loop: ClosedLoop, condition: Condition, xi_samples: Tensor, region: Region,
                     validation: Tensor | None = None, asked: SetAsked | None = None,
                     local: bool = False) -> AcceptanceCheck:
    """Run all three checks; ``passed`` is True only if all of them pass.

    ``xi_samples (N, k)``: every sample; the Jacobian and equilibrium checks run at each of them and at
    their mean (the condition uses its own samples: the baseline's only the mean). ``validation``: the
    states of the first check (default: ``region.grid()``). ``asked``: the sublevel set the pair is trained for
    (:class:`SetAsked`; None: the condition on all of the validation states, no faces).
    ``local_rates``: V's second-order decay rate at x* on each of the condition's samples
    (:func:`~drlyap.conditions.local_rates`), always reported; with ``local`` every one must be negative.
    """
    level = None if asked is None else asked.level
    z = region.grid() if validation is None else validation
    inside = z
    boundary_min = None
    if asked is not None:
        inside = z[(loop.value(z) <= level).to(z.device)]
        faces = asked.faces
        if faces is None:
            faces = region.sample_faces(20000, torch.Generator().manual_seed(12345))
        face_values = loop.value(faces)
        boundary_min = float(face_values.min())
        above = boundary_min > level if asked.face_levels is None else bool(
            (face_values.double() > asked.face_levels.to(face_values.device, torch.float64)).all())
    residual = condition_residual(loop, condition, inside) if inside.shape[0] else torch.empty(0)
    max_violation = float(residual.max()) if residual.numel() else -math.inf
    jac = jacobian_check(loop, xi_samples)
    equilibria = find_equilibria(loop, xi_samples, region.delta)
    if level is not None and equilibria:
        values = loop.value(torch.tensor([e["local"] for e in equilibria]))  # in V's dtype and device
        for e, v in zip(equilibria, values.tolist()):
            e.update(value=v, in_set=bool(v <= level))
    blocking = [e for e in equilibria if e.get("in_set", True)]
    with torch.enable_grad():
        rates = [float(r) for r in local_rates(condition, loop).detach().cpu()]
    passed = (max_violation <= 0) and jac["hurwitz"] and not blocking
    if local:
        passed = passed and all(r < 0 for r in rates)  # NaN fails
    if level is not None:
        passed = passed and above
    return AcceptanceCheck(passed=bool(passed and not math.isnan(max_violation)), validation_states=int(z.shape[0]),
                           max_violation=max_violation,
                           violating_fraction=float((residual > 0).double().sum()) / max(1, int(z.shape[0])),
                           jacobian=jac, other_equilibria=equilibria, level=level, boundary_min=boundary_min,
                           local_rates=rates,
                           local_rate_max=math.nan if any(math.isnan(r) for r in rates) else max(rates))


class PairKeeper:
    """A fit's acceptance checks (:func:`acceptance_check` on the fixed ``validation``
    states, with a level also 20,000 states inside the set) and the best pair so far: a passing one first, then by
    :meth:`~drlyap.records.AcceptanceCheck.stability`, the violating share and the largest violation; while the set
    grows, the latest pair that passes."""

    def __init__(self, loop: ClosedLoop, condition: Condition, xi: Tensor, region: Region, validation: Tensor,
                 states: TrainingStates, local: bool, growing: bool) -> None:
        self.loop, self.condition, self.xi, self.region, self.validation = loop, condition, xi, region, validation
        self.states, self.local, self.growing = states, local, growing
        self.checks: list[dict] = []
        self.best: tuple | None = None
        self.seconds = 0.0

    def check(self, iteration: int) -> AcceptanceCheck:
        """Check the pair as it is now; keep it where it ranks above the best so far. Returns the check."""
        tic = time.perf_counter()
        level, lyapunov = self.states.level, self.loop.lyapunov
        validation = self.validation
        if level is not None:  # the set is a few % of the box: add 20,000 states drawn inside it (fixed seed)
            inside = inside_states(lyapunov, self.region, level, 20000, self.states.device,
                                   torch.Generator().manual_seed(12345))
            validation = torch.cat([validation, inside])
        faces = self.states.check_faces(self.loop, self.condition.xi)
        asked = None if level is None else SetAsked(level, *(faces or ()))
        check = acceptance_check(self.loop, self.condition, self.xi, self.region, validation=validation, asked=asked,
                                 local=self.local)
        check.iteration = iteration
        self.checks.append(check.summary())
        score = (*check.stability(), -check.violating_fraction, -check.max_violation)
        if self.growing and check.passed:  # a growing set: the latest pair that passes holds the largest set
            score = (*check.stability(), iteration)
        if self.best is None or score > self.best[0]:
            self.best = (score, *snapshot(lyapunov, self.loop.controller), check)
        self.seconds += time.perf_counter() - tic
        return check

    def restore(self, iteration: int) -> AcceptanceCheck:
        """Load the best pair into the networks (checking the last one first where it was not); its check."""
        if self.best is None or (self.checks and self.checks[-1]["iteration"] != iteration):
            self.check(iteration)
        _, v_state, c_state, check = self.best
        restore(self.loop.lyapunov, self.loop.controller, (v_state, c_state))
        return check


def snapshot(lyapunov: Lyapunov, controller: Controller) -> tuple[dict, dict]:
    """Copies of both networks' weights."""
    return copy.deepcopy(lyapunov.state_dict()), copy.deepcopy(controller.state_dict())


def restore(lyapunov: Lyapunov, controller: Controller, states: tuple[dict, dict]) -> None:
    """Load the weights of a :func:`snapshot` into the networks (in place)."""
    lyapunov.load_state_dict(states[0])
    controller.load_state_dict(states[1])
