"""What each step of the region-of-attraction route returns (:mod:`drlyap.verification.roa`), as typed results.

:func:`~drlyap.verification.roa.certify.certified_roa` runs the steps and
:func:`~drlyap.verification.roa.sublevel.finish` adds them up to a
:class:`~drlyap.verification.results.RegionOfAttraction`, which holds them for the JSON (``roa.local``,
``roa.quadratic``, ``roa.band``, ``roa.strict``) and for the certificates (:mod:`drlyap.workflows.record`):

* :class:`Strictness` -- whether the decrease outside the delta-ball is strict (``outer_strictness``);
* :class:`LocalProof` -- V's own decrease inside the delta-ball (``local_decrease``), with its :class:`RingProof`;
* :class:`EllipsoidCandidate`, :class:`QuadraticRegion` -- the closed loop's own ellipsoid ``{z^T P z <= c_q}``
  (``quadratic_roa``), with the search beyond its cube (:class:`EllipsoidSearch`);
* :class:`LinearisationProof` -- V's sublevel sets inside that ellipsoid (``linearisation_local``), with its
  :class:`Annulus`;
* :class:`BandRegion` -- V's decrease outside the ellipsoid (``band_roa``), one :class:`LevelTry` per level tried.
* :class:`RouteSteps` -- the steps that ran, as ``finish`` takes them.

Each ``to_dict()`` is the JSON the route has always written; ``from_dict()`` reads it back. Fields in ``OPTIONAL`` are
left out while they are None (a step that stopped early writes only what it found).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

from drlyap.verification.result_base import Result


@dataclass
class Strictness(Result):
    """Whether the condition's decrease outside the delta-ball is strict, ``Vdot < 0``: ``by`` ``"decay"``
    (gamma > 0), ``"form"`` (alpha > 0 and V > 0 by its form), ``"proof"`` (alpha > 0 and V > 0 on X_delta proved,
    ``lower`` its bound) or None; the proof's ``boxes``, ``time_s``, ``stopped``, and ``reason`` where it is not."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("lower", "boxes", "time_s", "stopped", "reason")
    strict: bool
    by: str | None
    lower: float | None = None
    boxes: int | None = None
    time_s: float | None = None
    stopped: str | None = None
    reason: str | None = None


@dataclass
class RingProof(Result):
    """The decrease ``Vdot + decay_rate ||z|| <= 0`` proved between the second-order cube and the delta-ball (outside
    the ball of radius ``inner_radius``): the branch and bound's status, boxes, proved share and why it stopped."""

    status: str = ""
    decay_rate: float = 0.0
    inner_radius: float = 0.0
    boxes: int = 0
    verified_fraction: float = 0.0
    stopped: str = ""


@dataclass
class LocalProof(Result):
    """V's own decrease inside the delta-ball (:func:`~drlyap.verification.roa.local.local_decrease`): ``method``
    ``"second order"`` or ``"mean-value Jacobian"``, ``proved``, the cube's half-widths ``cube`` and its bound
    ``hessian_bound``, the ``ring`` proof, ``boxes``, ``reason`` where it fails; ``equilibrium`` where x* is an
    equilibrium of every sample's model (a failure is then one of the proof itself), ``local_rate`` V's second-order
    rate at x* where the cube proof failed, ``capped`` the steps stopped at their time cap."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("equilibrium", "local_rate", "capped", "time_s")
    NESTED: ClassVar[dict[str, type]] = {"ring": RingProof}
    method: str
    proved: bool = False
    cube: list[float] | None = None
    hessian_bound: float | None = None
    ring: RingProof | None = None
    reason: str = ""
    boxes: int = 0
    equilibrium: bool | None = None
    local_rate: float | None = None
    capped: list[str] | None = None
    time_s: float | None = None


@dataclass
class EllipsoidSearch(Result):
    """The search of ``W = z^T P z``'s sublevel sets beyond its proved box (``sublevel_roa`` on W): its level, kind,
    what limited it, boxes and seconds, with the ring's decay, inner radius and enclosure."""

    level: float | None = None
    kind: str | None = None
    limited_by: str | None = None
    boxes_processed: int = 0
    time_s: float = 0.0
    decay_rate: float = 0.0
    inner_radius: float = 0.0
    enclosure: str | None = None


@dataclass
class EllipsoidCandidate(Result):
    """One candidate ``W = z^T P z`` of :func:`~drlyap.verification.roa.quadratic.quadratic_roa` (``P_choice``: how P
    was chosen): ``Wdot < 0`` proved on the cube ``cube`` (``cube_fraction`` of the box's half-widths, bound
    ``hessian_bound``) and on the box ``box`` around ``{W <= box_level}``; ``{W <= q_level}`` certified
    (``share_of_box`` its exact volume over the box's, ``extent`` its largest ``|z_i|``); ``cube_level`` the largest
    ellipsoid inside the cube, ``q_roa`` the search beyond it, ``boxes`` its boxes; ``inner_level`` (set by the
    linearisation proof) V's lower bound outside it."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("inner_level",)
    NESTED: ClassVar[dict[str, type]] = {"q_roa": EllipsoidSearch}
    P: list[list[float]] | None = None
    q_level: float | None = None
    share_of_box: float | None = None
    extent: list[float] | None = None
    cube: list[float] | None = None
    cube_fraction: float | None = None
    hessian_bound: float | None = None
    cube_level: float | None = None
    box_level: float | None = None
    box: list[float] | None = None
    q_roa: EllipsoidSearch | None = None
    boxes: int = 0
    P_choice: str = ""
    inner_level: float | None = None


_CHOSEN = ("P", "q_level", "share_of_box", "extent", "cube", "cube_fraction", "hessian_bound", "cube_level", "box_level",
           "box", "q_roa", "P_choice")
"""The fields of an :class:`EllipsoidCandidate` that a :class:`QuadraticRegion` holds for the one it chose."""


@dataclass
class QuadraticRegion(Result):
    """The closed loop's own certified ellipsoid (:func:`~drlyap.verification.roa.quadratic.quadratic_roa`):
    ``proved``, the chosen candidate's fields (``P``, ``q_level``, ``share_of_box``, ...: :class:`EllipsoidCandidate`),
    ``candidates`` (every one tried, each with its P), ``boxes`` (all the searches'), the Jacobians and their
    eigenvalues (left out where the region is reported), ``reason`` where it fails."""

    OPTIONAL: ClassVar[tuple[str, ...]] = (
        "jacobians", "eigenvalues", "P", "extent", "cube", "cube_fraction", "hessian_bound", "cube_level", "box_level",
        "box", "q_roa", "P_choice", "candidates", "time_s", "capped")
    NESTED: ClassVar[dict[str, type]] = {"q_roa": EllipsoidSearch, "candidates": EllipsoidCandidate}
    method: str = "linearisation"
    proved: bool = False
    q_level: float | None = None
    share_of_box: float = 0.0
    reason: str = ""
    boxes: int = 0
    jacobians: list | None = None
    eigenvalues: list | None = None
    P: list[list[float]] | None = None
    extent: list[float] | None = None
    cube: list[float] | None = None
    cube_fraction: float | None = None
    hessian_bound: float | None = None
    cube_level: float | None = None
    box_level: float | None = None
    box: list[float] | None = None
    q_roa: EllipsoidSearch | None = None
    P_choice: str | None = None
    candidates: list[EllipsoidCandidate] | None = None
    time_s: float | None = None
    capped: list[str] | None = None

    def ellipsoid(self) -> EllipsoidCandidate | None:
        """The chosen ellipsoid, where one is certified (None otherwise; its ``boxes`` are all the searches')."""
        if not self.proved:
            return None
        return EllipsoidCandidate(**{k: getattr(self, k) for k in _CHOSEN}, boxes=self.boxes)

    def choose(self, candidate: EllipsoidCandidate) -> QuadraticRegion:
        """This result with ``candidate`` as the chosen ellipsoid (its fields copied; ``proved``)."""
        return replace(self, **{k: getattr(candidate, k) for k in _CHOSEN}, proved=True)

    def reported(self) -> QuadraticRegion:
        """What a region reports of it: everything but the Jacobians and their eigenvalues (the candidates shared)."""
        return replace(self, jacobians=None, eigenvalues=None)


@dataclass
class Annulus(Result):
    """V's strict decrease (``decay_rate`` gamma, ``exp_rate`` alpha) on ``{c_1 <= V <= c}`` inside the delta-ball
    (``region`` ``"delta-ball"``, or ``"box"`` where the condition has no decay): the level it holds to, what limited
    it, boxes, the boxes' minimum width and a counterexample (user coordinates) where one stopped it."""

    level: float = 0.0
    limited_by: str = ""
    boxes: int = 0
    decay_rate: float = 0.0
    exp_rate: float = 0.0
    region: str = ""
    min_width: float = 0.0
    counterexample: list[float] | None = None


@dataclass
class LinearisationProof(Result):
    """V's sublevel sets from the closed loop's linearisation
    (:func:`~drlyap.verification.roa.quadratic.linearisation_local`): ``proved``, ``level`` (the largest ``c' <= c``
    the chain holds for), the ellipsoid it rests on (``P``, ``q_level``, ``cube``), ``inner_level`` ``c_1``,
    ``quadratic`` (the ellipsoid search, :class:`QuadraticRegion`), the ``annulus``, ``boxes``, ``reason`` where it
    fails; ``second_order``: V's own proof near x*, which failed (set by ``certified_roa``)."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("jacobians", "eigenvalues", "P", "cube", "inner_level", "annulus", "time_s",
                                           "capped", "second_order")
    NESTED: ClassVar[dict[str, type]] = {"quadratic": QuadraticRegion, "annulus": Annulus, "second_order": LocalProof}
    method: str = "linearisation"
    proved: bool = False
    level: float | None = None
    reason: str = ""
    boxes: int = 0
    quadratic: QuadraticRegion | None = None
    jacobians: list | None = None
    eigenvalues: list | None = None
    P: list[list[float]] | None = None
    q_level: float | None = None
    cube: list[float] | None = None
    inner_level: float | None = None
    annulus: Annulus | None = None
    time_s: float | None = None
    capped: list[str] | None = None
    second_order: LocalProof | None = None


@dataclass
class LevelTry(Result):
    """One level the band proof tried: whether its search reached it, its boxes and the seconds since the start."""

    level: float = 0.0
    reached: bool = False
    boxes: int = 0
    time_s: float = 0.0


@dataclass
class BandRegion(Result):
    """V's strict decrease outside the closed loop's ellipsoid (:func:`~drlyap.verification.roa.band.band_roa`):
    ``proved`` (``level > 0``), ``level``, ``limited_by``, the ellipsoid (``P``, ``q_level``) and V's sampled range
    on its boundary (``v_on_ellipsoid``), ``beyond_ellipsoid`` (the set reaches outside it, sampled), the levels
    tried, boxes, seconds, a counterexample (user coordinates) and ``reason`` where it fails."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ("P", "q_level", "v_on_ellipsoid", "capped", "boxes", "decay_rate", "levels",
                                           "beyond_ellipsoid", "counterexample", "time_s")
    NESTED: ClassVar[dict[str, type]] = {"levels": LevelTry}
    method: str = "band"
    proved: bool = False
    level: float | None = None
    limited_by: str | None = None
    reason: str = ""
    P: list[list[float]] | None = None
    q_level: float | None = None
    v_on_ellipsoid: list[float] | None = None
    capped: list[str] | None = None
    boxes: int | None = None
    decay_rate: float | None = None
    levels: list[LevelTry] | None = None
    beyond_ellipsoid: bool | None = None
    counterexample: list[float] | None = None
    time_s: float | None = None

    def to_dict(self) -> dict:
        out = super().to_dict()
        if self.boxes is not None:  # the search ran: it says whether it stopped at a counterexample
            out["counterexample"] = self.counterexample
        return out


NearProof = LocalProof | LinearisationProof | BandRegion
"""What ``RegionOfAttraction.local`` holds: how the set was proved near x*."""


@dataclass
class RouteSteps:
    """The steps of the route that :func:`~drlyap.verification.roa.sublevel.finish` adds up: the proof near x*
    (``local``), and where they ran the closed loop's ellipsoid, the band proof and the strictness of the decrease
    outside the ball."""

    local: NearProof
    quadratic: QuadraticRegion | None = None
    band: BandRegion | None = None
    strict: Strictness | None = None


def near_proof_from_dict(data: dict | None) -> NearProof | None:
    """The proof near x* as its ``to_dict`` wrote it, by its ``method``."""
    if not data:
        return None
    kind = {"linearisation": LinearisationProof, "band": BandRegion}.get(data.get("method"), LocalProof)
    return kind.from_dict(data)


__all__ = ["Annulus", "BandRegion", "EllipsoidCandidate", "EllipsoidSearch", "LevelTry", "LinearisationProof",
           "LocalProof", "NearProof", "QuadraticRegion", "RingProof", "RouteSteps", "Strictness", "near_proof_from_dict"]
