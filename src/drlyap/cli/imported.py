"""``drlyap import``: a controller (and optionally V) from ONNX files for a system, as a run directory of kind
``imported`` that ``drlyap compare`` proves like any other pair."""

from __future__ import annotations

import json
from pathlib import Path

import click

from drlyap.cli.common import command_hint, fail, recorded_source, refuse_early


@click.command("import")
@click.argument("system")
@click.option("--controller", "controller", type=click.Path(path_type=Path, dir_okay=False), required=True,
              help="ONNX model of the controller: x (batch, n) -> u (batch, m), e.g. drlyap export's controller.onnx.")
@click.option("--lyapunov", "lyapunov", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="ONNX model of the Lyapunov function V: x (batch, n) -> V (batch,), its minimum at x*; what is "
                   "proved is V less its value and slope there, V(x) - V(x*) - grad V(x*).(x - x*) [none: z'Pz of "
                   "the closed loop's linearisation at x*, A'P + PA = -S^-2].")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Run directory to create.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (run_dir, checks, notes) on stdout.")
def import_pair(system: str, controller: Path, lyapunov: Path | None, out: Path, as_json: bool) -> None:
    """Import a controller (and V) for SYSTEM from ONNX files, read as data: only a small set of operations is
    accepted (Gemm, MatMul, Add, Sub, Mul, Div, Neg, Tanh, Relu, Sigmoid, Exp, Pow, Clip, Min/Max with constants,
    ReduceSum, Cast, Identity, batch-keeping reshapes, shape arithmetic); anything else is refused. The input
    prefix x - x* with the angle wrap that `drlyap export` writes is removed when it matches SYSTEM.

    Then `drlyap verify OUT --xi ... --roa` proves decrease on the true model and certifies a region of attraction
    as for a trained pair, and `drlyap compare` puts it beside other runs. SYSTEM is a registered name,
    package.module:factory or path/to/file.py:factory."""
    refuse_early(systems=[system])
    from drlyap.runs.publish import check_writable

    try:  # before the files and torch load
        check_writable(out)
    except ValueError as err:
        fail(err)

    from drlyap.runs.imported import import_run

    try:
        pair = import_run(system, controller, out, lyapunov)
    except ValueError as err:
        fail(err)
    sys_ = pair.loop.system
    if as_json:
        click.echo(json.dumps({"run_dir": str(out), "system": sys_.name, "certificate": pair.certificate,
                               "decay_rate": pair.decay_rate, "exp_rate": pair.exp_rate, "checks": pair.checks,
                               "notes": pair.notes}))
        return
    click.echo(f"imported a {sys_.name} pair into {out}")
    click.echo(f"  controller: {controller.name}, {pair.loop.controller.describe()}")
    for note in pair.notes.get("controller", []):
        click.echo(f"    {note}")
    if pair.certificate == "quadratic":
        eig = ", ".join(f"{re:.4g}{im:+.4g}j" for re, im in pair.checks["eigenvalues"])
        click.echo(f"  certificate: z'Pz of the closed loop's linearisation (eigenvalues {eig}); decay "
                   f"{pair.exp_rate:.3g} z'Pz")
    else:
        graph = getattr(pair.loop.lyapunov, "graph", pair.loop.lyapunov)
        click.echo(f"  certificate: V from {lyapunov.name}, {graph.describe()}; decay "
                   f"{pair.decay_rate:g} ||z|| + {pair.exp_rate:g} V "
                   + ("(its run's)" if pair.delta is not None else "(plain decrease)"))
        for note in pair.notes.get("lyapunov", []):
            click.echo(f"    {note}")
    offset = ", ".join(f"{v:.3g}" for v in pair.checks["pi_minus_u_star"])
    click.echo(f"  at x*: pi(x*) - u* = ({offset})")
    if sys_.test_xi is not None:
        where, xi = "", ",".join(f"{v:g}" for v in sys_.test_xi)
    else:  # no test shift declared: the nominal model, xi = 0
        where, xi = " on the nominal model (--xi: another shift)", ",".join("0" for _ in range(sys_.k))
    click.echo(f"  prove it{where}: {command_hint('verify', out, '--xi', xi, '--roa', source=recorded_source(out))}")
