"""Certified regions of attraction (:func:`certified_roa`) and the proofs they rest on, one module each:
:mod:`~drlyap.verification.roa.sublevel` (V's sublevel sets by V's own proofs), :mod:`~drlyap.verification.roa.local`
(V's decrease near x*), :mod:`~drlyap.verification.roa.quadratic` (the closed loop's linearisation and its
ellipsoid), :mod:`~drlyap.verification.roa.band` (V's decrease outside that ellipsoid) and
:mod:`~drlyap.verification.roa.levels` (the level search they share)."""

from drlyap.verification.roa.band import band_proof, band_roa
from drlyap.verification.roa.certify import REGION_RATE, certified_roa, region_rate
from drlyap.verification.roa.local import local_decrease
from drlyap.verification.roa.quadratic import ellipsoid_proof, linearisation_local, linearisation_proofs, quadratic_roa
from drlyap.verification.roa.sublevel import share_of_box, sublevel_roa

__all__ = ["REGION_RATE", "band_proof", "band_roa", "certified_roa", "ellipsoid_proof", "linearisation_local",
           "linearisation_proofs", "local_decrease", "quadratic_roa", "region_rate", "share_of_box", "sublevel_roa"]
