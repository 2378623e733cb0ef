"""A trained pair out of Python (``drlyap export RUN``): the controller and V as ONNX models or TorchScript
modules that a robot's runtime can load, with a record of what was proved about them.

Both models take the state in **user coordinates** (``x``, float64, ``(batch, n)``, the system's state order and
units) and do what :meth:`drlyap.runs.Run.controller` and :meth:`~drlyap.runs.Run.lyapunov` do: the offset to
x*, angles wrapped into ``[-pi, pi)``, the networks in float32, outputs in float64 (the controller's u* added in
float64 in place of its float32 rounding, so that ``pi(x*) = u*`` exactly). The controller includes
its saturation to the input box U: ``u`` (``(batch, m)``) never leaves U (a last clamp in float64 removes the
float32 rounding by which the network's ``u* + sat(.)`` can pass a bound). ``V`` is ``(batch,)``.

Written into ``OUT`` (default ``RUN/export``): ``controller.onnx`` and ``lyapunov.onnx`` (or ``controller.pt`` and
``lyapunov.pt``, TorchScript), and ``export.json``: the input and output names and units, the system's description,
the sha256 of the run's ``weights.pt`` and of each exported file, and the run's certificate (what its proof
rounds proved: condition, region, status). The ONNX files carry the same record in their metadata
(``drlyap`` key).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from pathlib import Path

import torch
from torch import Tensor, nn

from drlyap.io import jsonable, write_bytes_of, write_json
from drlyap.runs import Run, atomic_dir, check_writable

FORMATS = ("onnx", "torchscript")
OPSET = 17


class UserCoordinates(nn.Module):
    """``net`` applied to user-coordinate states: ``x (B, n)`` float64 -> ``net(to_local(x))`` in float64, with the
    same arithmetic as :meth:`drlyap.systems.UncertainSystem.to_local` (offset to x*, angles wrapped); with
    ``box`` (U's bounds) the output is clamped to it in float64. With ``u_star`` (the controller's u*, float64)
    the float32 network's own u* is replaced by it: ``net(z) - float32(u*) + u*`` in float64, so that
    ``pi(x*) = u*`` exactly, as in the run (a float32 u* is off by a rounding: the quadrotor's hover thrust by 7e-8
    N, which makes x* no equilibrium of the exported loop)."""

    def __init__(self, net: nn.Module, equilibrium, angle_dims, box=None, u_star=None) -> None:
        super().__init__()
        self.net = net
        self.recentred = u_star is not None
        us = torch.as_tensor(u_star if u_star is not None else (0.0,), dtype=torch.float64).reshape(1, -1)
        self.register_buffer("u_star", us)
        self.register_buffer("u_star32", us.float().double())
        self.bounded = box is not None
        lo, hi = box if box is not None else ((0.0,), (0.0,))
        self.register_buffer("low", torch.tensor([lo], dtype=torch.float64))
        self.register_buffer("high", torch.tensor([hi], dtype=torch.float64))
        self.register_buffer("x_star", torch.tensor([equilibrium], dtype=torch.float64))
        mask = torch.zeros(1, len(equilibrium), dtype=torch.bool)
        mask[0, list(angle_dims)] = True
        self.register_buffer("angles", mask)
        self.wrap = bool(angle_dims)

    def forward(self, x: Tensor) -> Tensor:
        z = x - self.x_star
        if self.wrap:
            z = torch.where(self.angles, torch.remainder(z + math.pi, 2 * math.pi) - math.pi, z)
        out = self.net(z.float()).double()
        if self.recentred:
            out = (out - self.u_star32) + self.u_star
        if self.bounded:  # u* + sat(.) in float32 can pass U's bounds by a float32 rounding (measured: 3.8e-8)
            out = torch.minimum(torch.maximum(out, self.low), self.high)
        return out


def exported_modules(run: Run) -> dict[str, UserCoordinates]:
    """The two modules to export, on the CPU in eval mode: ``controller`` and ``lyapunov``."""
    system = run.system
    out = {}
    controller = run.controller_net
    for name, net, box, u_star in (("controller", controller, system.input_box, getattr(controller, "u_star", None)),
                                   ("lyapunov", run.lyapunov_net, None, None)):  # drlyap's controllers hold u*
        out[name] = UserCoordinates(net, system.equilibrium, system.angle_dims, box, u_star).cpu().eval()
    return out


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def export_record(run: Run, fmt: str) -> dict:
    """What ``export.json`` says about the exported models (without the files' own hashes)."""
    system = run.system
    units = list(system.state_units) or [""] * system.n
    return jsonable({
        "format": fmt, "system": system.describe(), "run_dir": str(run.path), "method": run.config.method,
        "weights_sha256": _sha256(run.path / "weights.pt"),
        "inputs": {"x": {"shape": ["batch", system.n], "dtype": "float64", "order": list(system.state_names),
                         "units": units, "coordinates": "user (not offset to x*)"}},
        "outputs": {"controller": {"u": {"shape": ["batch", system.m], "dtype": "float64",
                                         "order": list(system.input_names),
                                         "units": list(system.input_units) or [""] * system.m,
                                         "box": [list(b) for b in system.input_box]}},
                    "lyapunov": {"V": {"shape": ["batch"], "dtype": "float64"}}},
        "certificate": run.metrics.get("certificate"),
        "claim": {"decay_rate": run.config.decay_rate, "exp_rate": run.config.exp_rate, "level": run.config.roa_level,
                  "delta": run.config.delta},
    })


def _onnx(module: nn.Module, example: Tensor, path: Path, output: str, record: dict) -> None:
    try:
        import onnx
    except ImportError:
        raise ValueError("ONNX export needs onnx: pip install 'drlyap[export]'") from None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript-based exporter announces its successor
        torch.onnx.export(module, (example,), str(path), dynamo=False, opset_version=OPSET, input_names=["x"],
                          output_names=[output], dynamic_axes={"x": {0: "batch"}, output: {0: "batch"}})
    model = onnx.load(str(path))
    entry = model.metadata_props.add()
    entry.key, entry.value = "drlyap", json.dumps(record)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def export_run(run: Run, out: str | os.PathLike | None = None, fmt: str = "onnx") -> dict:
    """Write the run's controller and V in ``fmt`` (``onnx`` or ``torchscript``) into ``out`` (default
    ``RUN/export``; a new directory, written atomically). Returns the ``export.json`` record with ``files``."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; valid: {', '.join(FORMATS)}")
    out = Path(out) if out is not None else run.path / "export"
    check_writable(out)
    modules = exported_modules(run)
    example = torch.tensor([run.system.equilibrium], dtype=torch.float64).repeat(2, 1)
    record = export_record(run, fmt)
    outputs = {"controller": "u", "lyapunov": "V"}

    def fill(tmp: Path) -> None:
        files = {}
        for name, module in modules.items():
            if fmt == "onnx":
                path = tmp / f"{name}.onnx"
                _onnx(module, example, path, outputs[name], record)
            else:
                path = tmp / f"{name}.pt"
                with torch.no_grad(), warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # TorchScript announces its successor too
                    traced = torch.jit.trace(module, (example,))
                write_bytes_of(path, lambda buffer, m=traced: torch.jit.save(m, buffer))  # a failed write: an OSError
            files[name] = {"file": path.name, "sha256": _sha256(path)}
        record["files"] = files
        write_json(tmp / "export.json", record)

    atomic_dir(out, fill)
    return record
