"""Certified robustness: the largest Wasserstein radius, and the largest box of parameter shifts, that a pair
(V, pi) provably tolerates over a region X_delta.

Both are found by bisection on *proofs* of the branch-and-bound verifier (:func:`verify_condition`); every
number reported as certified was proved, never sampled.

**Wasserstein radius** (:func:`certified_radius`). The pointwise DR residual is, at a state z,
``rho(z, r) = CVaR_eps_j(Vdot_j(z) + decay(z)) + (r/eps) ||W^T grad V(z)||`` (the r-term adds the same
amount to every sample, and the CVaR is translation-equivariant), so it is non-decreasing in r: a proof at
r covers every smaller radius, and the condition holds for exactly ``r <= r_true = eps inf_z (-rho(z, 0) /
lip(z))``. A dense set of states gives the sampled ratio ``r_s >= r_true`` (a real state violates the
condition for every r > r_s); the search proves r = 0, then guesses just below r_s, and bisects
(geometrically, or just below the unproved end once the bracket is narrow: :data:`NEAR`) on proofs until the
bracket ``[proved, unproved)`` is within a relative tolerance. The direct route -- a branch and bound on the ratio
itself -- would need a sound lower bound of ``-rho / lip`` on boxes where lip may vanish; the bisection reuses the
verifier unchanged and, started from the sampled ratio, usually needs two or three proofs.

**Shift box** (:func:`certified_shift_box`). The largest s such that plain decrease on the TRUE model,
``grad V . F(x, pi(x), p0 + xi) + decay <= 0``, is proved for every xi in the box ``[-s scale, s scale]`` at
once (:class:`TrueDecrease` with an :class:`Interval` of xi; the boxes are nested, so proofs are monotone in
s). Corners of the box evaluated at dense states give the sampled upper end.

A run directory's searches: :func:`drlyap.workflows.verify.run_robustness`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRPointwise, TrueDecrease
from drlyap.enclosures import F64, Interval
from drlyap.kinds import Enclosure, Status
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.systems import UncertainSystem
from drlyap.verification.branch_and_bound import ProofRules, StartFrom, verify_condition
from drlyap.verification.partition import PROVED, Partition
from drlyap.verification.results import CertifiedRadius, CertifiedShiftBox

SEARCH_BUDGET = Budget(seconds=10.0, enclosure=Enclosure.MEAN_VALUE)
"""The default budget of each proof of a search."""


@dataclass(frozen=True)
class SearchLimits:
    """How far a robustness search goes: ``tol`` the relative width of its final bracket ``[v*, v_unproved)``,
    ``total_time`` seconds (a cap) and ``max_proofs`` proofs of the whole search (the bracket found so far is returned,
    with ``stopped`` saying why), ``cap`` the largest value tried (None: the search's own, :data:`RADIUS_CAP` or
    :data:`SHIFT_CAP`)."""

    tol: float = 0.01
    total_time: float = 120.0
    max_proofs: int = 40
    cap: float | None = None

    def __post_init__(self) -> None:
        if not self.tol > 0:
            raise ValueError(f"tol must be > 0, got {self.tol}")

    def capped(self, default: float) -> float:
        return default if self.cap is None else float(self.cap)


RADIUS_CAP = 1e6
"""The largest Wasserstein radius a search tries, unless its limits say otherwise."""
SHIFT_CAP = 1e3
"""The largest shift box (in multiples of its scale) a search tries, unless its limits say otherwise."""

NEAR = 16
"""Within this many tolerances of the proved end, after a proof that held, a search probes the lowest value whose proof
would end it (``unproved / (1 + tol)``) before it bisects again: the edge of what a proof's budget reaches sits just
below a value it gave up at (on the quadrotor the radius search's last five bisections and the shift box's last four
were all proved, 230-255 s and 135-154 s each). Where that probe fails, the search bisects below it."""


# --------------------------------------------------------------------------- dense states
def dense_states(region: Region, per_axis: int = 200, sphere: int = 2000, seed: int = 0) -> Tensor:
    """States ``(B, n)`` of X_delta for the sampled upper ends: a grid with the box's faces (``per_axis`` points
    per axis, ends included, for n <= 3; else the region's Sobol set) plus ``sphere`` states on the sphere
    ``||z|| = delta`` inside the box (violations often sit on the faces or just outside the ball)."""
    if region.n <= 3:
        per = per_axis if region.n <= 2 else 40
        axes = [torch.linspace(float(a), float(b), per, dtype=F64) for a, b in zip(region.lo, region.hi)]
        z = torch.cartesian_prod(*axes).reshape(-1, region.n)
        z = z[region.contains(z)]
    else:
        z = region.grid(per_axis)
    if region.delta > 0 and sphere > 0:
        g = torch.Generator().manual_seed(seed)
        d = torch.randn(sphere, region.n, generator=g, dtype=F64)
        s = d / d.norm(dim=-1, keepdim=True) * region.delta * (1 + 1e-9)
        s = s[((s >= region.lo) & (s <= region.hi)).all(-1)]
        z = torch.cat([z, s])
    return z


def _in_sublevel(loop: ClosedLoop, z: Tensor, level: float | None, batch: int = 8192) -> Tensor:
    """The states of ``z (B, n)`` with ``V <= level`` (all of them without a level), by the float64 networks."""
    if level is None:
        return z
    with torch.no_grad():
        v = torch.cat([loop.f64.lyapunov(z[i:i + batch]) for i in range(0, z.shape[0], batch)])
    return z[v <= level]


def _residuals(loop: ClosedLoop, condition, z: Tensor, batch: int = 8192) -> Tensor:
    """The residual ``(B,)`` of ``condition`` at ``z`` with the float64 networks (the arithmetic of the claims)."""
    f64 = loop.f64
    with torch.no_grad():
        return torch.cat([f64.residual(condition, z[i:i + batch]) for i in range(0, z.shape[0], batch)])


def _residuals_and_lip(loop: ClosedLoop, condition, z: Tensor, batch: int = 8192) -> tuple[Tensor, Tensor]:
    """``(residual (B,), lip (B,))`` of a DR condition at ``z`` with the float64 networks."""
    f64 = loop.f64
    res, lip = [], []
    with torch.no_grad():
        for i in range(0, z.shape[0], batch):
            t = condition.terms(f64, z[i:i + batch])
            res.append(condition.residual(t))
            lip.append(t.lip)
    return torch.cat(res), torch.cat(lip)


# --------------------------------------------------------------------------- the search
class _Search:
    """One bisection on proofs: its probes so far, the proofs they cost, its clock, and the bracket ``[lo, hi_res)``
    (``lo`` proved, ``hi_res`` the probe above it that failed, None until one fails)."""

    def __init__(self, prove: Callable[[float], dict], refute: Callable[[float], dict | None],
                 limits: SearchLimits) -> None:
        self.prove, self.refute, self.limits = prove, refute, limits
        self.clock = time.perf_counter()
        self.probes: list[dict] = []
        self.proofs = 0
        self.lo: float | None = None
        self.hi_res: dict | None = None

    def probe(self, v: float) -> dict:
        """``refute(v)``, else the proof at v, recorded with what decided it."""
        res = self.refute(v)
        if res is None:
            res = self.prove(v)
            self.proofs += 1
            res["by"] = "verifier"
        else:
            res["by"] = "sampled state"
        res["value"] = v
        self.probes.append({"value": v, "status": res["status"], "by": res["by"], "time_s": res.get("time_s")})
        return res

    def over_budget(self) -> bool:
        return self.proofs >= self.limits.max_proofs or time.perf_counter() - self.clock > self.limits.total_time

    def out(self, stopped: str, reason: str | None = None) -> dict:
        """The search's outcome with the bracket it holds now."""
        return _bracket(self.lo, self.hi_res, stopped, reason) | {"proofs": self.proofs, "probes": self.probes,
                                                                  "time_s": time.perf_counter() - self.clock}

    def begin(self, proved: float | None) -> bool:
        """Start from ``proved`` (a value proved already), else from a proof at 0; False where 0 is not proved."""
        if proved is not None and proved > 0:
            self.probes.append({"value": proved, "status": Status.VERIFIED, "by": "an earlier proof", "time_s": None})
            self.lo = float(proved)
            return True
        first = self.probe(0.0)
        if first["status"] != Status.VERIFIED:
            self.hi_res = first
            return False
        self.lo = 0.0
        return True

    def try_guess(self, guess: float | None) -> None:
        """Probe just below, then just above, a sampled upper end (the property fails just above it)."""
        if guess is None or not math.isfinite(guess) or not guess > 0:
            return
        tol, cap = self.limits.tol, float(self.limits.cap)
        for v in (min(guess * (1 - tol / 2), cap), min(guess * (1 + tol / 4), cap)):
            if v <= self.lo:
                continue
            res = self.probe(v)
            if res["status"] == Status.VERIFIED:
                self.lo = v
            else:
                self.hi_res = res
                break

    def grow(self, start: float) -> dict | None:
        """Grow by 4x (from ``start`` where nothing above 0 is proved) until a probe fails; the outcome where the cap or
        the budget comes first, else None."""
        cap = float(self.limits.cap)
        v = start
        while self.hi_res is None:
            if self.lo > 0:
                v = self.lo * 4
            if self.lo >= cap:
                return self.out("cap", f"proved up to the cap {cap:g}")
            v = min(v, cap)
            if self.over_budget():
                return self.out("budget", "time or proof budget ran out while growing")
            res = self.probe(v)
            if res["status"] == Status.VERIFIED:
                self.lo = v
            else:
                self.hi_res = res
        return None

    def narrow(self, reguess: Callable[[dict], float | None] | None) -> dict:
        """Bisect the bracket until it is within the tolerance (or the budget runs out)."""
        tol = self.limits.tol
        guessed = False  # whether the last probe was placed just below a witness's value (and failed)
        rose = False  # whether the last probe was proved (the edge is then likelier near the upper end)
        while self.lo == 0 or self.hi_res["value"] / self.lo - 1 > tol:
            if self.over_budget():
                return self.out("budget")
            mid, guessed, top = self._next_value(reguess, guessed, rose)
            if mid <= 1e-300:
                return self.out("vanishing", "unproved at every value tried above 0")
            res = self.probe(mid)
            rose = res["status"] == Status.VERIFIED
            if rose:
                self.lo, guessed = mid, False
            else:
                self.hi_res = res
                self.hi_res["topped"] = top  # where the top failed, the search bisects below it
        return self.out("tolerance")

    def _next_value(self, reguess: Callable[[dict], float | None] | None, guessed: bool,
                    rose: bool) -> tuple[float, bool, bool]:
        """The next value to probe inside the bracket, whether it sits just below a witness's value, and whether it is
        the top (the lowest value whose proof ends the search): the geometric midpoint, else just below a new sampled
        upper end (never twice in a row), else, after a proof that held near the upper end, the top (:data:`NEAR`)."""
        lo, hi_res, tol = self.lo, self.hi_res, self.limits.tol
        hi = hi_res["value"]
        mid = math.sqrt(lo * hi) if lo > 0 else hi / 4
        again = None
        if reguess is not None and hi_res.get("witness") and not hi_res.get("reguessed") and not guessed:
            again = reguess(hi_res)  # a guess from the witness, but never twice in a row: every other probe bisects
        hi_res["reguessed"] = True
        guessed = again is not None and lo < again * (1 - tol / 2) < hi
        if guessed:
            mid = again * (1 - tol / 2)
        top = rose and not guessed and hi / lo - 1 <= NEAR * tol and not hi_res.get("topped")
        if top:
            mid = hi / (1 + 0.999 * tol)  # the lowest value whose proof ends the search, where it holds
        return mid, guessed, top


def _largest_proved(prove: Callable[[float], dict], refute: Callable[[float], dict | None], guess: float | None,
                    start: float, limits: SearchLimits,
                    reguess: Callable[[dict], float | None] | None = None, proved: float | None = None) -> dict:
    """Largest v in ``[0, cap]`` with ``prove(v)['status'] == 'verified'``, for a property monotone in v, within
    ``limits`` (its tolerance, seconds, proofs and ``cap``, which must be set).

    ``refute(v)``: a cheap witness that v fails (a real evaluation), or None. ``guess``: a sampled upper end
    (the property fails just above it), or None (then grow geometrically from ``start``). ``reguess(res)``: a
    new sampled upper end from the witness of a failed proof (the verifier's counterexample), or None; the
    next probe is then just below it. ``proved``: a value already proved (the search starts there instead of
    proving 0). Returns the bracket ``proved <= v* < unproved``, what decided the upper end, and the probes made.
    """
    search = _Search(prove, refute, limits)
    if not search.begin(proved):
        return search.out("not provable at 0",
                          f"the condition is {search.hi_res['status']} already at 0 ({search.hi_res['by']})")
    search.try_guess(guess)
    ended = search.grow(start)
    if ended is not None:
        return ended
    return search.narrow(reguess)


def _bracket(lo: float | None, hi_res: dict | None, stopped: str, reason: str | None) -> dict:
    """A search's outcome: the proved value ``lo``, the probe ``hi_res`` above it that failed, and why it stopped."""
    hi = None if hi_res is None else hi_res["value"]
    return {"certified": lo, "unproved": hi, "unproved_status": None if hi_res is None else hi_res["status"],
            "unproved_by": None if hi_res is None else hi_res["by"],
            "witness": None if hi_res is None else hi_res.get("witness"),
            "relative_gap": (hi / lo - 1) if (lo and hi is not None) else None, "stopped": stopped, "reason": reason}


def _prover(loop: ClosedLoop, region: Region, budget: Budget, make, level: float | None,
            start: tuple[float, Partition] | None = None) -> tuple[Callable[[float], dict], dict]:
    """``prove(v)``: the proof of ``make(v)``, ended at its first counterexample or as soon as it cannot finish within
    its budget (more boxes queued than it has left), for a property monotone in v (what holds at v holds below it).

    Every proof starts from the partition of the one before it (``start``: a partition proved at a value already, or
    at ``-inf``: a tree to start from), whose nodes each carry the largest value their box is proved at (a box inside
    one proved at v is proved at v; ``-inf``: none yet): a proof at v keeps the leaves proved at v or above, and bounds
    the others again (split further where they must be). A proof that fails still leaves what it proved above v for
    the proofs below it (and the boxes it split stay split: bounding them whole again, where nothing below them
    stands, cost 6% more boxes on the quadrotor's radius search). Also returns ``{"value", "proof"}``: the largest
    value verified by one of these proofs and its :class:`~drlyap.verification.results.ConditionProof` (with its
    partition).
    """
    enclosure = budget.enclosure_for(loop.n)
    base: dict = {"partition": None, "grade": None}
    best: dict = {"value": None, "proof": None}
    if start is not None and start[1].enclosure == enclosure:
        part = start[1]
        base["partition"] = part
        base["grade"] = part.inherit_max(torch.where(part.verdict == PROVED, float(start[0]), -math.inf)
                                         .to(torch.float64))

    def prove(v: float) -> dict:
        part, grade = base["partition"], base["grade"]
        standing = None if part is None else grade >= v
        try:
            r = verify_condition(loop, make(v), region, budget, level=level,
                                 start=None if part is None else StartFrom(part, standing),
                                 rules=ProofRules(stop_at_counterexample=True, give_up=True, keep_partition=True))
        except ValueError as err:  # e.g. the dynamics are undefined for some shift in the box (a zero mass)
            return {"status": "error", "error": str(err), "time_s": None}
        res = {"status": r.status, "time_s": r.time_s, "verified_fraction": r.verified_fraction,
               "boxes": r.boxes_processed}
        if r.counterexample is not None:
            res["witness"] = {"state": r.counterexample, "residual": r.counterexample_value}
        if r.verified and (best["value"] is None or v > best["value"]):
            best["value"], best["proof"] = v, r
        if r.partition is not None:  # its tree extends the one it started from: grades carry over by node
            new = r.partition
            values = torch.full((new.size,), -math.inf, dtype=torch.float64)
            if part is not None:
                values[:part.size] = grade
            values = torch.where(new.verdict == PROVED, values.clamp(min=v), values)
            base["partition"], base["grade"] = new, new.inherit_max(values)
        return res

    return prove, best


# --------------------------------------------------------------------------- radius
def certified_radius(loop: ClosedLoop, condition: DRPointwise, region: Region, budget: Budget = SEARCH_BUDGET, *,
                     limits: SearchLimits = SearchLimits(), level: float | None = None, proved: float | None = None,
                     start: Partition | None = None) -> CertifiedRadius:
    """The largest Wasserstein radius r for which the pointwise DR condition (at the condition's risk level
    eps, samples and decay) is proved over the region X_delta (``level``: over its sublevel set ``{V <= level}``,
    the set a region-of-attraction run is trained and proved on; sampled refutations are then taken there too).

    ``condition``: a :class:`DRPointwise` (its own radius is only reported; the search sets r with
    :meth:`~DRPointwise.with_radius`). ``budget``: of each proof; ``limits``: of the whole search (:class:`SearchLimits`:
    the final bracket's relative width, seconds, proofs, the largest radius tried). ``proved``: a radius at
    which this very condition (risk level, samples, decay, region, level) is already proved, e.g. by the run's trained
    condition: the search starts there (its first probe, ``by`` ``an earlier proof``) instead of proving r = 0;
    ``start``: that proof's partition, which the search's proofs start from instead of the grid (see :func:`_prover`:
    what a proof proved at a radius stands for every proof at a smaller one). Each proof of the search ends
    at its first counterexample, or as soon as it cannot finish within its budget (unknown).

    Returns a :class:`~drlyap.verification.results.CertifiedRadius`: ``radius`` (r*, proved: the condition holds for
    every r <= r*; None when it is not provable even at r = 0, with ``reason``), ``unproved`` (the smallest radius tried
    that is not proved, ``unproved_status`` ``violated``/``unknown``/``error`` and ``unproved_by`` ``verifier`` or
    ``sampled state``, with the ``witness`` state where the residual is > 0), ``sampled_upper`` (``eps min_z -rho(z,
    0)/lip(z)`` over dense states: the condition fails above it), ``proofs``, ``probes``, ``time_s``, and ``proof``: the
    search's own proof at r*, with its partition (None where r* is ``proved``'s). """
    if not isinstance(condition, DRPointwise):
        raise ValueError(f"certified_radius needs a DRPointwise condition, got {type(condition).__name__}")
    system = loop.system
    clock = time.perf_counter()
    z = _in_sublevel(loop, dense_states(region), level)
    res0, lip = _residuals_and_lip(loop, condition.with_radius(0.0), z)
    best: dict = {"sampled": math.inf, "at": None}  # the smallest sampled ratio and its state

    def take(states: Tensor, r0: Tensor, lips: Tensor) -> None:
        positive = lips > 0
        if bool((r0 <= 0).all()) and bool(positive.any()):
            ratio = torch.where(positive, -r0 / torch.where(positive, lips, 1.0), torch.inf)
            i = int(ratio.argmin())
            if condition.eps * float(ratio[i]) < best["sampled"]:
                best["sampled"], best["at"] = condition.eps * float(ratio[i]), states[i]

    take(z, res0, lip)
    first_guess = best["sampled"]

    def refute(r: float) -> dict | None:
        if r == 0.0:
            if bool((res0 > 0).any()):
                i = int(res0.argmax())
                return {"status": Status.VIOLATED, "witness": _witness(system, z[i], float(res0[i]))}
            return None
        at = best["at"]
        if at is None or r <= best["sampled"]:
            return None
        value = float(_residuals(loop, condition.with_radius(r), at[None])[0])
        return {"status": Status.VIOLATED, "witness": _witness(system, at, value)} if value > 0 else None

    def reguess(res: dict) -> float | None:  # the ratio at the verifier's counterexample
        state = system.to_local(torch.tensor([res["witness"]["state"]], dtype=F64))
        r0, lips = _residuals_and_lip(loop, condition.with_radius(0.0), state)
        before = best["sampled"]
        take(state, r0, lips)
        return best["sampled"] if best["sampled"] < before else None

    prove, best_proof = _prover(loop, region, budget, condition.with_radius, level,
                                None if proved is None or start is None else (proved, start))
    first = condition.r if condition.r > 0 else 1e-3
    found = _largest_proved(prove, refute, first_guess, first, replace(limits, cap=limits.capped(RADIUS_CAP)), reguess,
                            proved)
    found["time_s"] = time.perf_counter() - clock
    radius = found.pop("certified")
    sampled = best["sampled"]
    own = best_proof["proof"] if radius is not None and best_proof["value"] == radius else None
    return CertifiedRadius(radius=radius, **found, proof=own, sampled_upper=sampled if math.isfinite(sampled) else None,
                           risk_level=condition.eps, n_samples=int(condition.xi.shape[0]),
                           decay_rate=condition.decay_rate, exp_rate=condition.exp_rate, condition_radius=condition.r,
                           delta=region.delta, level=level)


def _witness(system: UncertainSystem, z: Tensor, value: float) -> dict:
    return {"state": system.to_user(z[None])[0].tolist(), "residual": value}


# --------------------------------------------------------------------------- shift box
def shift_scale(system: UncertainSystem, xi_samples: Tensor | None = None) -> Tensor:
    """Per uncertain parameter, the unit of the shift box ``(k,)``: ``|test_xi|`` where the system declares a
    nonzero test shift, else the standard deviation of ``xi_samples (N, k)`` where it is > 0, else 10% of
    ``|nominal value|`` (1 if that is 0)."""
    scale = torch.zeros(system.k, dtype=F64)
    nominal = torch.tensor(system.nominal_params, dtype=F64)[system.uncertain_index]
    std = None
    if xi_samples is not None and torch.as_tensor(xi_samples).shape[0] > 1:
        std = torch.as_tensor(xi_samples, dtype=F64).std(0)
    for i in range(system.k):
        test = abs(system.test_xi[i]) if system.test_xi is not None else 0.0
        if test > 0:
            scale[i] = test
        elif std is not None and float(std[i]) > 0:
            scale[i] = std[i]
        else:
            scale[i] = 0.1 * abs(float(nominal[i])) or 1.0
    return scale


def shift_box_condition(scale: Tensor, s: float, decay_rate: float, exp_rate: float = 0.0) -> TrueDecrease:
    """Plain decrease on the true model for every xi in ``[-s scale, s scale]`` (an interval ``(1, k)``)."""
    half = torch.as_tensor(scale, dtype=F64).reshape(1, -1) * s
    return TrueDecrease(Interval(-half, half), decay_rate, exp_rate)


def certified_shift_box(loop: ClosedLoop, region: Region, scale: Tensor, budget: Budget = SEARCH_BUDGET, *,
                        decay: tuple[float, float] = (0.0, 0.0), limits: SearchLimits = SearchLimits(),
                        level: float | None = None, start: Partition | None = None) -> CertifiedShiftBox:
    """The largest s such that decrease on the TRUE model, ``grad V . F(x, pi(x), p0 + xi) + decay_rate ||z||
    + exp_rate V <= 0`` (``decay = (decay_rate, exp_rate)``), is proved over X_delta for every shift xi in the box
    ``[-s scale, s scale]``.

    ``scale (k,)``: the box's half-widths at s = 1, in the uncertain parameters' units (see
    :func:`shift_scale`). ``start``: the partition of a proof of another condition on this region and level (e.g. the
    run's trained condition): the search's first proof starts from its tree (bounding its leaves again) instead of
    from the grid. Other arguments (``level`` too) as :func:`certified_radius`. Returns a
    :class:`~drlyap.verification.results.CertifiedShiftBox`: ``s`` (None when not provable
    even at xi = 0, with ``reason``), ``box`` (``{parameter: [low, high]}`` at s*, in the parameters' units),
    the bracket ``unproved`` / ``unproved_status`` / ``unproved_by`` / ``witness`` (a state and the corner
    shifts of the box there), ``sampled_upper`` (the smallest s at which a corner of the box violates the
    condition at a dense state, found by bisection on samples), ``proofs``, ``probes``, ``time_s``, and ``proof``:
    the search's own proof at s*, with its partition.
    """
    system = loop.system
    scale = torch.as_tensor(scale, dtype=F64).reshape(-1)
    if scale.shape[0] != system.k or not bool((scale > 0).all() and torch.isfinite(scale).all()):
        raise ValueError(f"scale must be {system.k} finite positive value(s) ({', '.join(system.uncertain)}), "
                         f"got {scale.tolist()}")
    decay_rate, exp_rate = (float(v) for v in decay)
    limits = replace(limits, cap=limits.capped(SHIFT_CAP))
    cap, tol = limits.cap, limits.tol
    clock = time.perf_counter()
    states = {"z": _in_sublevel(loop, dense_states(region), level)}

    def make(s: float) -> TrueDecrease:
        return shift_box_condition(scale, s, decay_rate, exp_rate)

    def refute_at(z: Tensor, s: float) -> dict | None:
        res = _residuals(loop, make(s), z)  # the max over the box's corners at each state
        bad = ~(res <= 0)  # non-finite counts as a failure
        if not bad.any():
            return None
        i = int(torch.where(bad, torch.nan_to_num(res, nan=math.inf), -math.inf).argmax())
        return {"status": Status.VIOLATED, "witness": _witness(system, z[i], float(res[i]))}

    def refute(s: float) -> dict | None:
        return refute_at(states["z"], s)

    def reguess(res: dict) -> float | None:  # the threshold at the verifier's counterexample
        state = system.to_local(torch.tensor([res["witness"]["state"]], dtype=F64))
        states["z"] = torch.cat([states["z"], state])
        return _sampled_threshold(lambda s: refute_at(state, s), cap, tol / 8)

    sampled = _sampled_threshold(refute, cap, tol / 8)
    prove, best = _prover(loop, region, budget, make, level, None if start is None else (-math.inf, start))
    found = _largest_proved(prove, refute, sampled, 1.0, limits, reguess)
    found["time_s"] = time.perf_counter() - clock
    s = found.pop("certified")
    box = None if s is None else {name: [-s * float(w), s * float(w)] for name, w in zip(system.uncertain, scale)}
    own = best["proof"] if s is not None and best["value"] == s else None
    return CertifiedShiftBox(s=s, box=box, **found, proof=own, scale=scale.tolist(), parameters=list(system.uncertain),
                             sampled_upper=sampled, decay_rate=float(decay_rate), exp_rate=float(exp_rate),
                             delta=region.delta, level=level)


def _sampled_threshold(refute: Callable[[float], dict | None], cap: float, tol: float) -> float | None:
    """The smallest s (to ``tol`` relative) at which ``refute`` finds a violation, by growth then bisection on
    samples; None if none is found up to ``cap``. Not a proof of anything: a guess for the proof search."""
    if refute(0.0) is not None:
        return 0.0
    lo, hi = 0.0, 1.0
    while refute(hi) is None:
        lo, hi = hi, hi * 2
        if hi > cap:
            return None
    for _ in range(60):
        if lo > 0 and hi / lo - 1 <= tol:
            break
        mid = math.sqrt(lo * hi) if lo > 0 else hi / 2
        if refute(mid) is None:
            lo = mid
        else:
            hi = mid
    return hi
