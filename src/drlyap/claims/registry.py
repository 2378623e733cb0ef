"""Every kind of claim drlyap states, gathered from the modules of :mod:`drlyap.claims` that define a ``KIND``
(:class:`~drlyap.claims.kind.ClaimKind`): a kind is added by adding its module. From them: the names of a run's
certificate files, which kinds each may state, a claim's kind read from its parts, and its sentence."""

from __future__ import annotations

import importlib
import pkgutil

import drlyap.claims as _package
from drlyap.claims.kind import ClaimKind
from drlyap.wording import UNREADABLE, condition_words


def _gather() -> tuple[ClaimKind, ...]:
    found = []
    for info in pkgutil.iter_modules(_package.__path__):
        kind = getattr(importlib.import_module(f"{_package.__name__}.{info.name}"), "KIND", None)
        if isinstance(kind, ClaimKind):
            found.append(kind)
    return tuple(sorted(found, key=lambda k: (k.rank, k.name)))


KINDS: tuple[ClaimKind, ...] = _gather()
"""The kinds of claim, in their order (``rank``)."""

BY_NAME: dict[str, ClaimKind] = {k.name: k for k in KINDS}

CLAIM_KINDS: tuple[str, ...] = tuple(BY_NAME)
"""The kinds' names: a decrease ``condition`` on X_delta or a sublevel set; the DR ``uniform`` condition (one
inequality); V's set resting on a ``core`` ellipsoid; V's decrease inside the delta-ball (``roa-ball``); the closed
loop's own quadratic region (``ellipsoid``); ``practical`` stability; the decrease on a ``band`` c1 <= V <= c2."""

CERTIFICATES: tuple[str, ...] = tuple(dict.fromkeys(f for k in KINDS for f in k.files))
"""The names of a run's certificate files, from every kind's ``files`` (each kind's module says what it claims)."""

KINDS_OF: dict[str, tuple[str, ...]] = {f: tuple(k.name for k in KINDS if f in k.files) for f in CERTIFICATES}
"""The kinds of claim each certificate file may state: what its name means, and what the checks that go by the name
(the run's agreement, a claim's premises) are written for."""


MARKS: tuple[str, ...] = tuple(dict.fromkeys(p for k in KINDS for p in k.parts))
"""The parts of a claim that mark its kind (a claim with none of them states a decrease condition)."""


def kinds_stating(name: str) -> tuple[ClaimKind, ...]:
    """The kinds the certificate file ``name`` may state (none for a name no kind gives its files)."""
    return tuple(BY_NAME[k] for k in KINDS_OF.get(name, ()))


def stated_kind(claim: dict) -> ClaimKind:
    """The kind a certificate's claim is stated as, from the parts that mark it (:data:`MARKS`) and whether its
    region is the delta-ball's box (``ball_of``); a ValueError where they make no kind drlyap states (two kinds at
    once, or a region in the ball's box for a claim whose words are about the whole box), so that a claim is never
    checked on less than its sentence says."""
    marks = frozenset(k for k in MARKS if claim.get(k) is not None)
    ball = claim["region"].get("ball_of") is not None
    kinds = [k for k in KINDS if k.states(marks, ball, claim)]
    if len(kinds) != 1:
        named = ", ".join(m for m in MARKS if m in marks) or "none"
        raise ValueError(f"the claim's parts ({named}) and its region "
                         f"({'the delta-ball' if ball else 'the state'}'s box) make no kind of claim drlyap states")
    return kinds[0]


def kind_of(claim: dict) -> ClaimKind:
    """The kind of a certificate's claim (:func:`stated_kind`), or a ValueError where its kind refuses what it states
    (:meth:`~drlyap.claims.kind.ClaimKind.refusal`)."""
    kind = stated_kind(claim)
    why = kind.refusal(claim)
    if why is not None:
        raise ValueError(why)
    return kind


def claim_kind(claim: dict) -> str:
    """The name of :func:`kind_of` the claim."""
    return kind_of(claim).name


def claim_sentence(claim: dict) -> str:
    """A certificate file's claim (``claim`` of its header: ``condition`` and ``region`` as written by
    :mod:`drlyap.runs.certificates`) in words, by its kind: what the file states and what ``drlyap check``
    re-proves."""
    try:
        kind = kind_of(claim)
        return kind.sentence(claim, condition_words(claim["condition"]) if kind.condition else "")
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, ArithmeticError):
        return UNREADABLE
