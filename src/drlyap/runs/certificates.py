"""Certificate files: a verified proof written down so that anyone can check it again (``drlyap check RUN``).

A certificate is two files in ``RUN/certificates/``: ``NAME.json``, the header, and ``NAME.npz``, the partition
the branch and bound proved the condition on (numpy arrays, read with ``allow_pickle=False``). ``NAME`` is
``trained`` (the run's trained condition), ``true-model`` (plain decrease on the true model at a shift, written by
``drlyap verify RUN --xi ...``), ``radius`` (the DR pointwise condition at the run's risk level, samples and decay
at the certified Wasserstein radius r*, written by ``drlyap verify RUN --max-radius``: the condition at every
smaller radius follows, the Wasserstein term growing with r), ``shift-box`` (decrease on the true model, with the
run's decay, for every shift in the certified box ``[-s* scale, s* scale]``, also written by ``--max-radius``),
``uniform`` (the DR uniform condition at the run's radius, risk level, samples and decay, one inequality over X_delta,
written by ``drlyap verify RUN --uniform``; a run trained on it writes it as ``trained``);
for a region of attraction (``verify --roa``), ``roa-ball`` (V's decrease on ``{V <= c}`` inside the delta-ball: a
``cube`` where it is proved by second order, the ring around it by a partition, ``outer`` the certificate of the
decrease outside the ball) and, where no other certificate states that decrease at c, ``roa``; where no sublevel set of
V is certified by V's own proofs but the closed loop's own quadratic region ``{z'Pz <= c_q}`` is, ``ellipsoid``
(``P``, ``c_q``, the box where W's decrease is proved by the Jacobian's enclosure and that proof's weights; a partition
where W's decrease is proved by boxes on the rest of the set).
A sublevel set of V certified through that ellipsoid (the linearisation route, the band proof) is a ``roa-ball``
(inside the delta-ball) or ``roa`` (the whole box) whose claim names it as its ``core``: V's strict decrease on the set,
boxes inside the ellipsoid being leaves of their own. Where only practical stability is proved (``verify --roa`` at a
shift that moves the equilibrium), ``practical``: V at most ``c0`` on the delta-ball (no partition: the checker bisects
the ball itself), naming as ``outer`` the certificate of the decrease outside it on ``{V <= c}``. ``band`` (``verify
--band``): decrease on the true model on ``{c1 <= V <= c2}`` of the whole box, the flow entering the box where
``V <= c2`` on its faces (:mod:`drlyap.verification.band_claim`). Each kind of claim is a module of
:mod:`drlyap.claims`, which names the files that may state it; a kind proved by name (``verify --claim NAME``) writes
its own file (:data:`drlyap.claims.registry.CERTIFICATES` lists them all).
The header (format ``drlyap-certificate``, version 1) holds:

* ``claim``: the condition (name, model, samples or shift ``xi`` or a box of shifts ``xi_box``, decay, Wasserstein
  radius and risk level), the region (the state box in local coordinates, ``delta``) and a sentence saying what is
  claimed;
* ``system``: its name and the sha256 of its description (``UncertainSystem.describe()`` as canonical JSON);
* ``networks``: the sha256 of ``weights.pt`` and V's ``alpha_hat`` (the rest of V and pi is in the weights);
* ``partition``: the arrays file, its sha256, the starting grid, the node count, the enclosure the proof used.

The partition's arrays (one entry per node, see :mod:`drlyap.verification.partition`): ``parent`` (int64),
``side``, ``axis``, ``verdict`` (int8) and ``bound`` (float64: the verifier's upper bound of the residual on proved
leaves, V's lower bound on leaves above a level). docs/run-directory.md describes the format and the checker.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from drlyap.claims.registry import CERTIFICATES, KINDS, MARKS, claim_sentence, kinds_stating, stated_kind
from drlyap.io import jsonable

if TYPE_CHECKING:  # the writing side's types; reading a certificate (the checker) loads nothing of the verifier
    from drlyap.conditions import Condition
    from drlyap.regions import Region
    from drlyap.systems import UncertainSystem
    from drlyap.verification.partition import Partition
    from drlyap.verification.results import ConditionProof, UniformMargin

FORMAT = "drlyap-certificate"
VERSION = 1
FOLDER = "certificates"
NAMES = CERTIFICATES
ARRAYS = ("parent", "side", "axis", "verdict", "bound")


def sha256_file(path: str | os.PathLike) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def networks_digest(contents: list[bytes]) -> str:
    """What a certificate names its networks by: the sha256 of ``weights.pt``'s bytes (one file), or for an imported
    pair (``graphs.json`` and ``tensors.pt``) the sha256 of their sha256s (hex) in that order."""
    if len(contents) == 1:
        return hashlib.sha256(contents[0]).hexdigest()
    return hashlib.sha256("".join(hashlib.sha256(c).hexdigest() for c in contents).encode()).hexdigest()


def system_digest(system: UncertainSystem) -> str:
    """sha256 of the system's description as canonical JSON (what a certificate names its system by)."""
    text = json.dumps(jsonable(system.describe()), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def condition_claim(condition: Condition) -> dict:
    """The condition as a certificate states it (what the checker rebuilds its residual from): the samples or shifts
    ``xi`` ``(N, k)``, or for a box of shifts (an interval ``xi``, the shift box) ``xi`` None and ``xi_box``
    ``{"low", "high"}`` ``(N, k)`` each."""
    from drlyap.enclosures import is_enclosure

    xi = condition.xi
    box = None
    if is_enclosure(xi):
        xi, box = None, {"low": xi.lo.tolist(), "high": xi.hi.tolist()}
    claim = condition.describe() | {"model": condition.model, "label": condition.label,
                                    "xi": xi.tolist() if xi is not None else None}
    return jsonable(claim if box is None else claim | {"xi_box": box})


def certificate_claim(condition: Condition | None, region: Region, level: float | None) -> dict:
    """What a certificate claims, as its header states it (without the sentence): the condition (None: a claim about
    no condition) and the region (the state box in local coordinates, delta, the level of a sublevel set or None)."""
    return jsonable({"condition": None if condition is None else condition_claim(condition),
                     "region": {"box_lo": region.lo.tolist(), "box_hi": region.hi.tolist(), "delta": region.delta,
                                "level": level, "coordinates": "local (z = x - x*)"}})


@dataclass(frozen=True)
class Stated:
    """What a certificate states: its ``condition`` (None: a claim about no condition), the ``region`` it holds on,
    the ``level`` of its sublevel set where no proof gives one (a claim without a partition), and the other ``parts``
    of its claim, as its kind writes them (:mod:`drlyap.claims`: ``cube``, ``outer``, ``ball_of`` for its region,
    ...)."""

    condition: Condition | None
    region: Region
    level: float | None = None
    parts: dict | None = None


@dataclass(frozen=True)
class PairFiles:
    """The files that hold the pair a certificate is about (``weights``: ``weights.pt``, or an imported pair's
    ``[graphs.json, tensors.pt]``: :func:`networks_digest`) and V's ``alpha_hat`` (None for an imported pair)."""

    weights: str | os.PathLike | list
    alpha_hat: float | None

    @classmethod
    def networks(cls, folder: str | os.PathLike, alpha_hat: float) -> PairFiles:
        """drlyap's own pair: ``folder/weights.pt`` and V's ``alpha_hat``."""
        return cls(Path(folder) / "weights.pt", float(alpha_hat))

    @classmethod
    def imported(cls, folder: str | os.PathLike) -> PairFiles:
        """An imported pair: ``folder/graphs.json`` and ``folder/tensors.pt``, no ``alpha_hat``."""
        return cls([Path(folder) / "graphs.json", Path(folder) / "tensors.pt"], None)


def certificate_header(proof: ConditionProof | UniformMargin | None, stated: Stated, system: UncertainSystem,
                       pair: PairFiles, arrays: tuple[str, str] | None) -> dict:
    """The JSON header of a certificate (see the module docstring): ``proof`` None for a claim without a partition;
    ``arrays``: the partition's file name and its sha256; ``pair``: the networks' digest is of its files."""
    extra = dict(stated.parts or {})
    claim = certificate_claim(stated.condition, stated.region, proof.level if proof is not None else stated.level)
    if "ball_of" in extra:
        claim["region"]["ball_of"] = float(extra.pop("ball_of"))
    claim |= jsonable(extra)
    part = None if proof is None else proof.partition
    files = pair.weights if isinstance(pair.weights, list) else [pair.weights]
    return jsonable({
        "format": FORMAT, "version": VERSION,
        "claim": {"statement": claim_sentence(claim), **claim},
        "system": {"name": system.name, "description_sha256": system_digest(system)},
        "networks": {"weights_sha256": networks_digest([Path(f).read_bytes() for f in files]),
                     "alpha_hat": pair.alpha_hat},
        "partition": None if part is None else {
            "file": arrays[0], "sha256": arrays[1], "grid": part.grid, "nodes": part.size,
            "enclosure": part.enclosure, "counts": part.counts()},
        "proof": None if proof is None else {"boxes_processed": proof.boxes_processed, "time_s": proof.time_s,
                                             "faces_min_lower": proof.boundary_min_lower}
        | ({"margin_upper": proof.margin_upper} if getattr(proof, "margin_upper", None) is not None else {}),
    })


def write_certificate(folder: str | os.PathLike, name: str, proof: ConditionProof | UniformMargin | None,
                      stated: Stated, system: UncertainSystem, pair: PairFiles) -> Path:
    """Write ``folder/certificates/NAME.json`` and ``.npz`` for a verified proof that kept its partition, stating
    ``stated`` about the pair in ``pair``'s files (``proof`` None: a claim of a kind without a partition, at
    ``stated.level``); each file is written to a temporary name and renamed, the header last. Returns the header's
    path."""
    if name not in NAMES:
        raise ValueError(f"unknown certificate name {name!r}; valid: {', '.join(NAMES)}")
    if proof is None and not _may_lack_partition(name):
        raise ValueError(f"a {name} certificate cannot be written without a proof: "
                         f"only {', '.join(n for n in NAMES if _may_lack_partition(n))}")
    if proof is not None and (proof.partition is None or not proof.verified):
        raise ValueError("only a verified proof that kept its partition can be written as a certificate")
    target = Path(folder) / FOLDER
    target.mkdir(exist_ok=True)
    arrays, digest = target / f"{name}.npz", None
    if proof is not None:
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **{k: getattr(proof.partition, k).numpy() for k in ARRAYS})
        data = buffer.getvalue()
        _replace(arrays, data)
        digest = hashlib.sha256(data).hexdigest()
    else:
        arrays.unlink(missing_ok=True)
    header = certificate_header(proof, stated, system, pair, None if proof is None else (arrays.name, digest))
    path = target / f"{name}.json"
    _replace(path, (json.dumps(header, indent=1) + "\n").encode())
    (target / f"{name}.check.json").unlink(missing_ok=True)  # a checker's record of the certificate this replaces
    return path


def _replace(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def remove_certificate(folder: str | os.PathLike, name: str) -> None:
    """Remove ``folder/certificates/NAME.*`` (header first, so that no header names arrays that are gone)."""
    target = Path(folder) / FOLDER
    for suffix in (".json", ".npz", ".check.json"):
        (target / f"{name}{suffix}").unlink(missing_ok=True)


def read_certificate(run_dir: str | os.PathLike, name: str) -> tuple[dict, dict[str, np.ndarray]]:
    """A certificate's header and arrays, read as data (``allow_pickle=False``), or a ValueError naming the file and
    what is wrong (missing, not JSON, another format, arrays that do not match the header's sha256)."""
    folder = Path(run_dir) / FOLDER
    path = folder / f"{name}.json"
    if not path.is_file():
        raise ValueError(f"{path} does not exist: no {name} certificate in {run_dir} "
                         "(a verified `drlyap train` or `drlyap verify` writes one)")
    try:
        header = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path} is damaged: {err}") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise ValueError(f"{path} is not a drlyap certificate")
    if header.get("version") != VERSION:
        raise ValueError(f"{path} has certificate version {header.get('version')!r}; this drlyap reads {VERSION}")
    if header.get("partition", False) is None and _without_partition(header.get("claim")):
        return header, {}  # a claim the checker proves without boxes (a cube, an ellipsoid, V on the ball)
    try:
        part = header["partition"]
        arrays_path = folder / Path(str(part["file"])).name
        data = arrays_path.read_bytes()
    except (KeyError, TypeError) as err:
        raise ValueError(f"{path}: no partition file named ({err})") from None
    except OSError as err:
        raise ValueError(f"{path}: its partition file cannot be read ({err.strerror or err})") from None
    if hashlib.sha256(data).hexdigest() != part.get("sha256"):
        raise ValueError(f"{arrays_path} does not match the sha256 in {path}: the partition was changed or damaged")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in ARRAYS}
    except (KeyError, ValueError, OSError) as err:
        raise ValueError(f"{arrays_path} is damaged: {err}") from None
    return header, arrays


def _may_lack_partition(name: str) -> bool:
    """Whether a kind the file ``name`` may state may have no partition."""
    return any(k.without_partition for k in kinds_stating(name))


def _without_partition(claim) -> bool:
    """Whether ``claim`` is stated as a kind whose certificate may have no partition, or has a part only such kinds
    have (what else it states, the checker judges)."""
    try:
        return stated_kind(claim).without_partition
    except ValueError:  # parts of several kinds: the checker names what is wrong
        only = set(MARKS) - {p for k in KINDS if not k.without_partition for p in k.parts}
        return any(claim.get(p) is not None for p in only)
    except (KeyError, TypeError, AttributeError):
        return False


def certificate_partition(run_dir: str | os.PathLike, name: str) -> Partition | None:
    """The partition of certificate ``name`` of a run (read as data, its sha256 compared with the header's), or None
    where there is none or it cannot be read."""
    from drlyap.verification.partition import Partition

    try:
        header, arrays = read_certificate(run_dir, name)
        part = header["partition"]
        return Partition(grid=[int(k) for k in part["grid"]], enclosure=str(part["enclosure"]),
                         parent=torch.as_tensor(arrays["parent"].astype(np.int64)),
                         side=torch.as_tensor(arrays["side"].astype(np.int8)),
                         axis=torch.as_tensor(arrays["axis"].astype(np.int8)),
                         verdict=torch.as_tensor(arrays["verdict"].astype(np.int8)),
                         bound=torch.as_tensor(arrays["bound"].astype(np.float64)))
    except (ValueError, KeyError, TypeError):
        return None
