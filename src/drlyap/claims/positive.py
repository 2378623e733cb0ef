"""V ``positive`` away from x*: ``V > 0`` at every state of the state box outside the open ball ``||x - x*|| <
delta`` (X_delta), the second of the field's Lyapunov conditions (V(x*) = 0, V > 0 elsewhere, V decreasing). drlyap's
own V is positive by its form; the claim states it for any V, an imported one included, and is proved by name:
``drlyap verify RUN --claim positive``. The verifier bounds V from below over X_delta by branch and bound
(:func:`~drlyap.verification.branch_and_bound.maximize` of -V); the checker re-proves it by its own bisection
(:func:`~drlyap.checker.levels.outside_positive`). No partition: the claim is V's alone, about no condition."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from drlyap.claims.kind import ClaimKind, ClaimOutcome, ClaimRequest
from drlyap.wording import condition_region, of_region

if TYPE_CHECKING:
    from drlyap.checker.reading import CheckResult, Reading


class Positive(ClaimKind):
    name = "positive"
    files = ("positive",)
    rank = 7
    parts = ("positive",)
    condition = False
    own_claim = True
    without_partition = True

    def states(self, marks: frozenset[str], ball: bool, claim: dict) -> bool:
        return marks == {"positive"} and not ball

    def refusal(self, claim: dict) -> str | None:
        if claim["region"].get("level") is not None or claim.get("condition") is not None:
            return "V's positivity is claimed on X_delta, about no condition: its claim states no level or condition"
        return None

    def sentence(self, claim: dict, what: str) -> str:
        region = of_region(condition_region(None, float(claim["region"]["delta"])))
        return f"V > 0 at every state of {region} (V is positive away from x*)"

    def before_partition(self, out: CheckResult, cert: Reading, header: dict, system) -> bool:
        """V > 0 on the box outside the open delta-ball by the checker's bisection (recorded in ``out``)."""
        from drlyap.checker.levels import outside_positive

        holds, out.positive_min, out.positive_boxes = outside_positive(cert.pair, cert.lo, cert.hi, cert.delta)
        out.proved = out.positive_boxes if holds else 0
        if not holds:
            out.failures.append(f"V > 0 outside the ball is not established (V's smallest lower bound there "
                                f"{out.positive_min:.6g}, {out.positive_boxes} boxes)")
        return False

    def prove_on(self, request: ClaimRequest) -> ClaimOutcome:
        """V's least value on X_delta bounded from below by branch and bound within the run's proof budget: verified
        where the bound is > 0 (the certificate ``positive`` is written; one written before stays otherwise), violated
        where a state of X_delta has ``V <= 0``, unknown where the budget ran out first."""
        from drlyap.regions import Domain, Region, default_grid
        from drlyap.runs.certificates import Stated, write_certificate
        from drlyap.verification.bounds import value_objective
        from drlyap.verification.branch_and_bound import maximize

        if not request.pinned:
            raise ValueError("V is not pinned at x* (imported as given): V > 0 away from x* is not its claim")
        start = time.perf_counter()
        loop = request.loop
        region = Region.of(loop.system, request.delta)
        least = value_objective(loop.lyapunov)
        lo, hi = region.boxes(default_grid(region.n))
        low, high, info = maximize(lambda z: -least(z), Domain(lo, hi, region.scale, region.meets, region.in_region),
                                   request.proof.budget(), rel_tol=0.5, label="V's least value on X_delta")
        lower, sampled = float(-high[0]), float(-low[0])  # V's sound lower bound; V's least value at a centre
        status = "verified" if lower > 0 else "violated" if sampled <= 0 else "unknown"
        numbers = {"lower": lower, "least_sampled": sampled, "boxes": info.boxes_processed, "stopped": info.stopped}
        sentence, path = f"V > 0 on X_delta ({status})", None
        if status == "verified":
            path = write_certificate(request.folder, self.name, None,
                                     Stated(None, region, parts={"positive": {"lower": lower}}), loop.system,
                                     request.files)
            sentence = self.sentence({"region": {"delta": region.delta}}, "")
        return ClaimOutcome(self.name, status, sentence, time.perf_counter() - start,
                            None if path is None else str(path), numbers)


KIND = Positive()
