"""Prove a claim by its kind's name (``drlyap verify RUN --claim NAME``): the kinds of :mod:`drlyap.claims` that
prove themselves (:attr:`~drlyap.claims.kind.ClaimKind.provable`) are asked here, on a loaded run and its proof
settings; each writes its own certificate where it is verified, which ``drlyap check`` re-proves by the same kind."""

from __future__ import annotations

from collections.abc import Sequence

from drlyap.claims.kind import ClaimOutcome, ClaimRequest
from drlyap.claims.registry import BY_NAME, KINDS
from drlyap.proof_settings import ProofConfig
from drlyap.runs import Run
from drlyap.workflows.verify import run_proof


def provable_claims() -> tuple[str, ...]:
    """The names of the kinds of claim proved by name."""
    return tuple(k.name for k in KINDS if k.provable)


def prove_claim(run: Run, name: str, proof: ProofConfig | None = None,
                xi: Sequence[float] | None = None) -> ClaimOutcome:
    """Prove the claim of the kind ``name`` for a loaded run (:func:`drlyap.runs.load_run`) with ``proof``'s settings
    (:func:`~drlyap.workflows.verify.run_proof`), at the shift ``xi`` where the kind is about one; its certificate is
    written into the run directory where it is verified. A ValueError names the kinds proved by name."""
    kind = BY_NAME.get(name)
    if kind is None or not kind.provable:
        raise ValueError(f"no claim {name!r} is proved by name; valid: {', '.join(provable_claims()) or 'none'}")
    shift = None if xi is None else tuple(float(v) for v in xi)
    return kind.prove(ClaimRequest(run, run_proof(run, proof), shift))
