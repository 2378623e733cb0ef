"""The closed loop's own quadratic region: ``{z'Pz <= c}`` (W = z'Pz, ``P`` in the claim) is a region of attraction,
W decreasing on it except at x*, by the Jacobian's enclosure over a box around x*; where the ellipsoid reaches
beyond that box (a ``ring``), by the decrease of W on a partition outside the delta-ball. Re-proved by
:mod:`drlyap.checker.ellipsoid`."""

from __future__ import annotations

from typing import TYPE_CHECKING

from drlyap.claims.kind import ClaimKind
from drlyap.wording import exact_text, half_widths_text, level_text

if TYPE_CHECKING:
    from drlyap.checker.reading import CheckResult, Reading


def ellipsoid_parts(p: list, level: float, box: list, tau: list, ring: bool) -> dict:
    """An ellipsoid claim's part as its certificate writes it: ``P`` (rows), its level, the box the Jacobian's test
    proved, that test's weights ``tau`` and whether a ring of boxes beyond it is proved."""
    return {"ellipsoid": {"P": p, "level": level, "box": box, "tau": tau, "ring": ring}}


class Ellipsoid(ClaimKind):
    name = "ellipsoid"
    files = ("ellipsoid",)
    rank = 4
    parts = ("ellipsoid",)
    without_partition = True

    def states(self, marks: frozenset[str], ball: bool, claim: dict) -> bool:
        return marks == {"ellipsoid"} and not ball

    def sentence(self, claim: dict, what: str) -> str:
        r = claim["region"]
        half = half_widths_text(claim["ellipsoid"]["box"])
        ring = "" if not claim["ellipsoid"].get("ring") else (
            f"; outside ||x - x*|| < {exact_text(float(r['delta']))}, "
            f"{what.replace('decrease', 'decrease of W', 1)} on it")
        return (f"{{z'Pz <= {level_text(r.get('level'))}}} (W = z'Pz, P in the file) is a region of attraction: W "
                f"decreases on it except at x*, on the box |x_i - x*_i| <= [{half}] by the Jacobian's enclosure{ring}")

    def about(self, out: CheckResult, claim: dict, pair):
        """W = z'Pz with the pair's controller: the claim is about W, not V."""
        import torch

        from drlyap.checker.arith import F64
        from drlyap.checker.ellipsoid import QuadraticPair

        return QuadraticPair(super().about(out, claim, pair), torch.as_tensor(claim["ellipsoid"]["P"], dtype=F64))

    def before_partition(self, out: CheckResult, cert: Reading, header: dict, system) -> bool:
        """The Jacobian's test on the box around x*; a partition follows where the claim has a ring."""
        from drlyap.checker.ellipsoid import ellipsoid_failures

        ring = header["partition"] is not None
        failures, out.cube_bound = ellipsoid_failures(cert.claim, cert.residual, cert.lo, cert.hi, cert.delta, ring)
        out.failures += failures
        return ring


KIND = Ellipsoid()
