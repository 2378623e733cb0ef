"""What every kind of claim is: the interface one module per kind (``drlyap/claims/<kind>.py``, its ``KIND``)
fills in, and :mod:`drlyap.claims.registry` gathers.

A kind says which parts of a certificate's claim mark it, which certificate files may state it, which certificates it
may rest on, the sentence it is printed as, and how the checker re-proves it: which pair it is about, what is
established before (or instead of) the partition's leaves, how the leaves are proved and what follows them. The
checker's own arithmetic is imported inside those methods, so that reading a claim's words loads no numerical code
(``drlyap --help`` lists the certificate names)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the checker's side of a claim: loaded only where a certificate is re-proved
    from drlyap.checker.reading import CheckResult, Leaves, Reading

PREMISES = {"outer": ("roa", "trained", "true-model"), "core": ("ellipsoid",)}
"""The certificates a claim may rest on, by the part of the claim that names them: the decrease outside the
delta-ball (``outer``) and the ellipsoid of its ``core`` (``core.certificate``)."""


@dataclass(frozen=True)
class ClaimRequest:
    """What a kind's proof is asked on: the pair's closed loop (:class:`~drlyap.closed_loop.ClosedLoop`; ``pinned``:
    whether its V is least at x*, False for an imported V taken as given), the run directory its certificate goes to
    (``folder``) with the files that hold the pair (``files``: :class:`~drlyap.runs.certificates.PairFiles`), the
    pair's ``delta``, its proof settings (:class:`~drlyap.proof_settings.ProofConfig`, resolved for the system) and a
    shift ``xi`` ``(k,)`` of the uncertain parameters where the claim is about the true model at one (None: the kind's
    default)."""

    loop: object
    folder: Path
    files: object
    delta: float
    proof: object
    xi: tuple[float, ...] | None = None
    pinned: bool = True


@dataclass
class ClaimOutcome:
    """How a kind's proof ended: ``status`` (``verified``, ``violated``, ``unknown``), the claim's ``sentence`` as its
    certificate states it (where one was written: ``certificate``, the header's path), ``time_s`` and the numbers
    behind it (``numbers``, JSON-ready)."""

    name: str
    status: str
    sentence: str
    time_s: float
    certificate: str | None = None
    numbers: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


class ClaimKind:
    """One kind of claim. ``name``: as :func:`~drlyap.claims.registry.claim_kind` returns it; ``files``: the
    certificate files that may state it (the checks that go by a file's name, its agreement with the run and its
    premises, are written for these); ``rank``: its place among the kinds (certificate files are listed in the order
    of the first kind that names them); ``rests_on``: the parts of its claim that name certificates it rests on
    (:data:`PREMISES`); ``parts``: the parts of a claim that mark this kind (the registry reads a claim's kind from
    every kind's parts); ``condition``: whether the claim is about a decrease condition (``claim["condition"]``);
    ``own_claim``: whether the claim states what it is about itself (its levels, shift, delta), so that nothing of
    the run's ``config.json`` or ``metrics.json`` is asked of it beside V's ``alpha_hat``; ``without_partition``:
    whether a certificate of it may have no partition (the checker proves it from the claim alone)."""

    name: str = ""
    files: tuple[str, ...] = ()
    rank: int = 0
    rests_on: tuple[str, ...] = ()
    parts: tuple[str, ...] = ()
    condition: bool = True
    own_claim: bool = False
    without_partition: bool = False

    def states(self, marks: frozenset[str], ball: bool, claim: dict) -> bool:
        """Whether a claim with the parts ``marks`` (of every kind's ``parts``), on the delta-ball's box (``ball``: its
        region has ``ball_of``) or the state box, is of this kind."""
        raise NotImplementedError

    @property
    def provable(self) -> bool:
        """Whether :meth:`prove_on` proves the claim here (the other kinds are proved by their own routes: ``verify``,
        ``verify --roa``, ``--band``, ``--max-radius``)."""
        return type(self).prove_on is not ClaimKind.prove_on

    def prove_on(self, request: ClaimRequest) -> ClaimOutcome:
        """Prove the claim of this kind for ``request``'s run and write its certificate where it is verified."""
        raise NotImplementedError(f"a {self.name} claim is proved by its own route, not by name")

    def refusal(self, claim: dict) -> str | None:
        """Why a claim of this kind states nothing drlyap claims (None: it states this kind's claim)."""
        return None

    def sentence(self, claim: dict, what: str) -> str:
        """The claim in words, ``what`` being its condition's (:func:`~drlyap.wording.condition_words`)."""
        raise NotImplementedError

    def about(self, out: CheckResult, claim: dict, pair):
        """The pair (V and pi, as the checker reads them) the claim is about; what its statement alone must say goes
        into ``out``. A V not pinned at x* (an imported V taken as given) is refused: only a claim about V as given
        may take it."""
        from drlyap.checker.reading import CertificateError

        if not getattr(pair, "pinned", True):
            raise CertificateError("V is not pinned at x* (graphs.json: imported as given): only a band claim is "
                                   "checked for it")
        return pair

    def floor(self, claim: dict) -> float | None:
        """A level below which the partition's leaves may lie instead of being proved (a band's ``c1``); None: none."""
        return None

    def before_partition(self, out: CheckResult, cert: Reading, header: dict, system) -> bool:
        """What the checker establishes before (or instead of) the partition's leaves, into ``out``; whether a
        partition follows."""
        return True

    def leaves(self, out: CheckResult, cert: Reading, leaves: Leaves, prove: Callable[[], None]) -> None:
        """The partition's proved leaves, re-proved: by ``prove`` (the checker's leaf by leaf proof) unless the kind
        proves them otherwise."""
        prove()

    def after_leaves(self, out: CheckResult, cert: Reading, leaves: Leaves) -> None:
        """What the kind establishes on the partition beside its proved leaves (a band's leaves below it)."""
