"""Prove a claim by its kind's name (``drlyap verify RUN --claim NAME``): the kinds of :mod:`drlyap.claims` that
prove themselves (:attr:`~drlyap.claims.kind.ClaimKind.provable`) are asked here, on a loaded run or imported pair
and its proof settings; each writes its own certificate where it is verified, which ``drlyap check`` re-proves by
the same kind."""

from __future__ import annotations

from collections.abc import Sequence

from drlyap.claims.kind import ClaimOutcome, ClaimRequest
from drlyap.claims.registry import BY_NAME, KINDS
from drlyap.proof_settings import ProofConfig
from drlyap.runs import PolicyRun, Run
from drlyap.runs.certificates import PairFiles
from drlyap.workflows.verify import run_proof


def provable_claims() -> tuple[str, ...]:
    """The names of the kinds of claim proved by name."""
    return tuple(k.name for k in KINDS if k.provable)


def claim_request(run: Run | PolicyRun, proof: ProofConfig | None = None,
                  xi: Sequence[float] | None = None) -> ClaimRequest:
    """What a kind's proof is asked on, for a loaded run (:func:`drlyap.runs.load_run`: its networks, delta and proof
    settings, :func:`~drlyap.workflows.verify.run_proof`) or an imported pair
    (:func:`drlyap.runs.load_imported_run`: its graphs, its export's delta or the system's, ``proof`` or the
    defaults)."""
    shift = None if xi is None else tuple(float(v) for v in xi)
    if isinstance(run, Run):
        return ClaimRequest(run.loop, run.path, PairFiles.networks(run.path, run.config.alpha_hat),
                            float(run.config.delta), run_proof(run, proof), shift)
    pair = run.info.get("pair")
    if pair is None:
        raise ValueError(f"{run.path} holds no pair drlyap proves claims of (a policy without V)")
    system = pair.loop.system
    delta = system.defaults.delta if pair.delta is None else pair.delta
    return ClaimRequest(pair.loop, run.path, PairFiles.imported(run.path), float(delta),
                        (proof or ProofConfig()).resolved(system), shift, pair.pinned)


def prove_claim(run: Run | PolicyRun, name: str, proof: ProofConfig | None = None,
                xi: Sequence[float] | None = None) -> ClaimOutcome:
    """Prove the claim of the kind ``name`` for a loaded run or imported pair (:func:`claim_request`), at the shift
    ``xi`` where the kind is about one; its certificate is written into the run directory where it is verified. A
    ValueError names the kinds proved by name."""
    kind = BY_NAME.get(name)
    if kind is None or not kind.provable:
        raise ValueError(f"no claim {name!r} is proved by name; valid: {', '.join(provable_claims()) or 'none'}")
    return kind.prove_on(claim_request(run, proof, xi))
