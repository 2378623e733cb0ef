"""``drlyap export``: a run's controller and V as ONNX models or TorchScript modules."""

from __future__ import annotations

import json
from pathlib import Path

import click

from drlyap.cli.common import fail, refuse_early, run_source_options, run_system_of


@click.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--format", "fmt", type=click.Choice(["onnx", "torchscript"]), default="onnx", show_default=True,
              help="ONNX (onnxruntime and most robot runtimes) or TorchScript (libtorch).")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Directory to create [RUN_DIR/export].")
@click.option("--json", "as_json", is_flag=True, help="Print the export record (export.json) as one JSON object.")
@run_source_options
def export(run_dir: Path, fmt: str, out: Path | None, as_json: bool, system_spec: str | None,
           trust_run: bool) -> None:
    """Write RUN_DIR's controller (with its saturation to U) and V as models that take the state in user
    coordinates (float64, the system's state order), with export.json: names, units, hashes and what was
    proved about the pair."""
    refuse_early(runs=[run_dir], systems=[system_spec])
    from drlyap.runs.publish import check_writable

    try:  # before the run and torch load
        check_writable(out if out is not None else run_dir / "export")
    except ValueError as err:
        fail(err)

    from drlyap.runs import load_run
    from drlyap.workflows.export import export_run

    try:
        run = load_run(run_dir, run_system_of(system_spec), trust_run)
        record = export_run(run, out, fmt)
    except ValueError as err:
        fail(err)
    if as_json:
        click.echo(json.dumps(record))
        return
    folder = out or run_dir / "export"
    cert = record.get("certificate") or {}
    files = ", ".join(f["file"] for f in record["files"].values())
    click.echo(f"wrote {folder} ({files}, export.json)")
    click.echo(f"  inputs: x (batch, {run.system.n}) float64 = ({', '.join(run.system.state_names)}), user "
               f"coordinates; outputs: u (batch, {run.system.m}) inside U, V (batch,)")
    click.echo(f"  the run's certificate as its metrics.json records it: {cert.get('status', 'none')} "
               f"({cert.get('condition', '-')}; `drlyap check` re-proves it); weights sha256 "
               f"{record['weights_sha256'][:16]}...")
