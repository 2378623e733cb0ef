"""``drlyap check``: re-check a run's certificate files with the independent checker."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import click

from drlyap.claims.registry import CERTIFICATES
from drlyap.cli.common import compute_options, compute_settings, fail, refuse_early, run_source_options, run_system_of


def _certificate_names(ctx: click.Context, param: click.Parameter, names: tuple[str, ...]) -> tuple[str, ...]:
    """``--name`` checked against the certificate files the kinds of claim name (a kind added adds its files)."""
    unknown = [n for n in names if n not in CERTIFICATES]
    if unknown:
        raise click.BadParameter(f"{unknown[0]!r} is no certificate's name; valid: {', '.join(CERTIFICATES)}")
    return names


@click.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--name", "names", multiple=True, metavar="NAME", callback=_certificate_names,
              help="Which certificate to check (repeatable), by its file's name (trained, true-model, roa, ...: the "
                   "error for an unknown one lists them all) [every one the run holds].")
@click.option("--refine", type=click.IntRange(0, 40), default=30, show_default=True,
              help="Times the checker may bisect a box its own bounds do not prove (the verifier's bounds may be "
                   "tighter than the checker's); it bounds at most as many pieces as each chunk of 16,384 leaves "
                   "has (at least 4,096), then the leaves still unproved once more with the pieces left over, so "
                   "a false certificate costs at most about twice a true one.")
@click.option("--pieces", "pieces_per_leaf", type=click.FloatRange(min=1.0), default=1.0, show_default=True,
              help="Pieces per leaf that bisection may bound in each of those two passes: more confirms a true "
                   "certificate whose hard leaves need many pieces, at most about 1 + this times the leaves' cost "
                   "for a false one.")
@compute_options()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@run_source_options
def check(run_dir: Path, names: tuple[str, ...], refine: int, pieces_per_leaf: float, workers: int, backend: str,
          address: str | None, device: str, as_json: bool, system_spec: str | None, trust_run: bool) -> None:
    """Re-check the certificates in RUN_DIR/certificates/ box by box with a small checker of its own (its own float64
    interval arithmetic, its own reading of V, pi and the condition), and say whether every box holds and the boxes
    cover the claimed region. Exits 1 when a certificate fails.

    A certificate is written by `drlyap train` and `drlyap verify` for every proof of a decrease condition that ends
    verified, on the state box minus the delta-ball or on a sublevel set {V <= c} of it: `trained`, `true-model`
    (verify --xi), `radius` and `shift-box` (verify --max-radius: the DR condition at the certified Wasserstein
    radius, and decrease on the true model for every shift in the certified box), `uniform` (verify --uniform: the
    DR uniform condition's margin, one inequality over the region; a run trained on it has it as `trained`), and
    for a region of attraction (verify --roa) `roa-ball`, V's decrease inside the delta-ball (Vdot's Hessian on a
    cube around x* and the ring around it, or outside the closed loop's certified ellipsoid), with `roa` where the
    decrease outside the ball on {V <= c} is not already another certificate's (or, for the band proof, V's decrease
    on {V <= c} outside that ellipsoid); `ellipsoid`, the closed loop's own quadratic region {z'Pz <= c} (W = z'Pz
    decreasing by the Jacobian's enclosure on a box, and by boxes beyond it); `practical`, for practical stability,
    V's bound on the delta-ball. A certificate that rests on another (a roa-ball on the decrease outside the ball,
    a region on its core's ellipsoid) is checked with it and fails where that one fails.

    What the checker confirms is recorded beside the certificate (NAME.check.json), sealed with a key that stays on
    this machine: `drlyap verify` takes only a record this machine sealed for these very files, never one that came
    with the run directory.
    """
    settings = compute_settings(workers, backend, address, device)
    if not math.isfinite(pieces_per_leaf):
        fail(ValueError(f"--pieces must be a finite number >= 1, got {pieces_per_leaf}"))
    refuse_early(runs=[run_dir], systems=[system_spec])

    from drlyap.checker import check_run
    from drlyap.render import check_lines

    try:
        results = check_run(run_dir, run_system_of(system_spec, verifier=False), trust_run, list(names) or None, refine,
                            settings, pieces_per_leaf)
    except ValueError as err:
        fail(err)
    except KeyboardInterrupt:
        click.echo("drlyap: interrupted; nothing was changed (the checker keeps no progress: run it again to check "
                   "from the start)", err=True)
        sys.exit(130)
    if as_json:
        click.echo(json.dumps({"ok": all(r.ok for r in results), "certificates": [r.to_dict() for r in results]}))
    else:
        for line in check_lines(results):
            click.echo(line)
    if not all(r.ok for r in results):
        sys.exit(1)
