"""A user's dynamics run once, when the system is loaded, through everything that will run them later: an operation
that training or a proof cannot take is refused before any training, with the file, the line and the operation.

:func:`probe_system` evaluates ``F(x, u, p)`` on one small batch (a few corners of the state box, its centre and x*,
inputs in U, nominal parameters) in each of the forms later code gives it:

* ``tensors``: float64 tensors (LQR, simulation, the verifier's float64 evaluations; the output must be a float64
  ``(B, n)`` tensor for ``B`` states, finite at these states, as :meth:`~drlyap.systems.UncertainSystem.check_finite`
  asks of the whole box), then float64 and float32 (the dtype training runs in) tensors with autograd:
  the design model ``f + W xi`` and its weighted form, with derivatives in ``x``, ``u`` and ``p``, as training takes
  them;
* ``verifier``: the verifier's enclosures (:mod:`drlyap.enclosures`): intervals at points and over small boxes,
  affine forms, dual numbers over both, the true model (also at an interval of shifts) and the design model's
  forward-mode derivatives in the uncertain parameters, as :mod:`drlyap.verification` and
  :mod:`drlyap.conditions` call them;
* ``checker``: the independent checker's own arithmetic (:mod:`drlyap.checker.arith`, :mod:`drlyap.checker.affine`),
  through its :class:`~drlyap.checker.model.Residual` (true and design models).

A failure is one :class:`ValueError` naming the system, the user's file and line (the deepest frame of the traceback
outside drlyap, torch, numpy, the standard library and installed packages, else the deepest in the dynamics' own
file, else the dynamics' ``def`` line), the operation when
it can be read from the error (``torch.abs is not supported by drlyap's verifier (dual numbers)``), the exception's
type and message, and the form the dynamics were run on. Passing groups are remembered per system object and per
dynamics (:func:`probe_system` runs each group once for the same dynamics, boxes and parameters).

The verifier's group imports :mod:`drlyap.enclosures`; ``verifier=None`` runs it only where this process has already
loaded them (training and proving have; ``drlyap check``, which must load nothing of the verifier, has not).
"""

from __future__ import annotations

import os
import re
import sys
import sysconfig
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

F64 = torch.float64
_PASSED: dict[tuple, set[str]] = {}  # dynamics fingerprint -> groups that passed (bounded: cleared past _CACHE_SIZE)
_CACHE_SIZE = 256
_ENCLOSURE_NAMES = ("Interval", "Affine", "Dual", "Iv", "Du", "Af")


class ProbeFailure(Exception):
    """One form's failure: the form's words, the exception, and a sentence when it is no exception of the user's
    code (a wrong shape or dtype)."""

    def __init__(self, form: str, error: BaseException | None = None, problem: str = "") -> None:
        super().__init__(problem or str(error))
        self.form, self.error, self.problem = form, error, problem


# --------------------------------------------------------------------------------------------- entry point
def probe_system(system, verifier: bool | None = True, checker: bool = True) -> None:
    """Run ``system``'s dynamics through the forms of the module docstring; a ValueError on the first that fails.

    ``verifier``: also the verifier's enclosures (None: only where :mod:`drlyap.enclosures` is already loaded);
    ``checker``: also the checker's arithmetic. Each passing group is remembered for this system object and for any
    system with the same dynamics, parameters, boxes and equilibrium, so a second call costs a dictionary look-up."""
    if verifier is None:
        verifier = "drlyap.enclosures" in sys.modules
    wanted = ["tensors", *(["verifier"] if verifier else []), *(["checker"] if checker else [])]
    done = system.__dict__.get("_probed")
    if done is None:
        key = _fingerprint(system)
        done = _PASSED.get(key) if key is not None else None
        if done is None:
            done = set()
            if key is not None:
                if len(_PASSED) >= _CACHE_SIZE:
                    _PASSED.clear()
                _PASSED[key] = done
        object.__setattr__(system, "_probed", done)
    todo = [g for g in wanted if g not in done]
    if not todo:
        return
    batch = _Batch(system)
    runs = {"tensors": _tensor_forms, "verifier": _verifier_forms, "checker": _checker_forms}
    unlocated: ValueError | None = None
    for group in todo:
        for form, run in runs[group](system, batch):
            try:
                with warnings.catch_warnings():  # what the user's code warns of, training will say again
                    warnings.simplefilter("ignore")
                    run()
            except ProbeFailure as failure:
                error = failure_error(system, failure)
                if failure.error is None or _user_frame(failure.error, system) is not None:
                    raise error from None
                unlocated = unlocated or error  # a later form may point at the line
            except Exception as err:  # noqa: BLE001 - the user's code may raise anything: it is reported, not hidden
                if _range_dependent(err):
                    continue
                error = failure_error(system, ProbeFailure(form, err))
                if _user_frame(err, system) is not None:
                    raise error from None
                unlocated = unlocated or error
        if unlocated is None:
            done.add(group)
    if unlocated is not None:
        raise unlocated


def _fingerprint(system) -> tuple | None:
    try:
        key = (system.dynamics, system.perturbation, system.state_names, system.input_names, system.param_names,
               system.nominal_params, system.uncertain, system.state_box, system.input_box, system.equilibrium,
               system.equilibrium_input)
        hash(key)
    except TypeError:  # an unhashable callable: the object's own memory only
        return None
    return key


def _range_dependent(err: Exception) -> bool:
    """An enclosure's refusal that depends on the range, not on the operation (a division by a range holding 0):
    where the verifier meets it, it splits the box."""
    return isinstance(err, ValueError) and "contains 0" in str(err)


# --------------------------------------------------------------------------------------------- the batch
class _Batch:
    """The probe's states (local ``z (B, n)``: a few corners of the state box, its centre, x*), inputs ``(B, m)``
    in U, small boxes ``[lo, hi]`` around the states (inside X) and a gain ``K (m, n)`` that makes the input an
    affine function of the state on enclosures (as the controller is), staying inside U."""

    def __init__(self, system) -> None:
        n, m = system.n, system.m
        xlo, xhi = (torch.tensor(b, dtype=F64) for b in system.state_box)
        ulo, uhi = (torch.tensor(b, dtype=F64) for b in system.input_box)
        x_star, u_star = torch.tensor(system.equilibrium, dtype=F64), torch.tensor(system.equilibrium_input, dtype=F64)
        patterns = [[0] * n, [1] * n, [i % 2 for i in range(n)], [(i + 1) % 2 for i in range(n)]]
        corners = [torch.where(torch.tensor(p, dtype=torch.bool), xhi, xlo) for p in patterns]
        unique = list({tuple(c.tolist()): c for c in corners}.values())
        x = torch.stack([*unique, (xlo + xhi) / 2, x_star])
        self.z = x - x_star
        rows = []
        for i in range(x.shape[0]):
            side = torch.tensor([(i + j) % 2 for j in range(m)], dtype=torch.bool)
            rows.append(u_star if i == x.shape[0] - 1 else u_star + 0.5 * (torch.where(side, uhi, ulo) - u_star))
        self.u = torch.stack(rows)
        half = (xhi - xlo) / 2
        self.lo = torch.maximum(x - 1e-3 * half, xlo) - x_star
        self.hi = torch.minimum(x + 1e-3 * half, xhi) - x_star
        u_half = torch.minimum(uhi - self.u, self.u - ulo).amin(0)  # the room every row has
        self.gain = 0.1 * u_half[:, None] / (n * 1e-3 * half[None, :])
        self.size = x.shape[0]


def _check_tensor(out, system, batch: int, dtype: torch.dtype, form: str, strict_dtype: bool) -> None:
    shape = (batch, system.n)
    if not isinstance(out, Tensor):
        raise ProbeFailure(form, problem=f"the dynamics returned a {type(out).__name__}, not a torch tensor of shape "
                                         f"(B, {system.n}) (B = {batch} states)")
    if tuple(out.shape) != shape:
        raise ProbeFailure(form, problem=f"the dynamics returned shape {tuple(out.shape)} for B = {batch} states, "
                                         f"expected (B, n) = {shape}: one row per state of the batch, one column per "
                                         f"state coordinate ({', '.join(system.state_names)})")
    if strict_dtype and out.dtype != dtype:
        raise ProbeFailure(form, problem=f"the dynamics returned {out.dtype} on {dtype} inputs: the output must keep "
                                         "the inputs' dtype (make constants with dtype=x.dtype; no .float())")
    if not out.dtype.is_floating_point:
        raise ProbeFailure(form, problem=f"the dynamics returned {out.dtype}, not a floating-point tensor")


# --------------------------------------------------------------------------------------------- the forms
def _tensor_forms(system, batch: _Batch) -> list[tuple[str, Callable[[], None]]]:
    b, n, m, p = batch.size, system.n, system.m, len(system.param_names)
    shapes = f"x ({b}, {n}), u ({b}, {m}), p ({b}, {p})"
    first = f"float64 tensors ({shapes})"

    def plain() -> None:
        x = system.to_user(batch.z)
        with torch.no_grad():
            out = system.dynamics(x, batch.u.clone(), system.params(None, x))
        _check_tensor(out, system, b, F64, first, strict_dtype=True)
        bad = ~torch.isfinite(out).all(-1)
        if bool(bad.any()):  # the words of UncertainSystem.check_finite, which asks the same of the whole box
            i = int(bad.nonzero()[0, 0])
            raise ProbeFailure(first, problem=f"{system.name}: the dynamics are not finite ({out[i].tolist()}) at x = "
                                              f"{[round(float(v), 6) for v in x[i]]}, u = "
                                              f"{[round(float(v), 6) for v in batch.u[i]]}; F must be finite on the "
                                              "whole state box and input set")

    def autograd(dtype: torch.dtype, form: str) -> tuple[str, Callable[[], None]]:
        def run() -> None:
            x = system.to_user(batch.z).to(dtype).requires_grad_(True)
            u = batch.u.to(dtype).requires_grad_(True)
            weights = torch.ones(b, n, dtype=dtype)
            with torch.enable_grad():
                out = system.true_dynamics(x, u, torch.zeros(system.k, dtype=dtype))
                _check_tensor(out, system, b, dtype, form, strict_dtype=False)
                f, w = system.design_model(x, u)
                s, gw = system.weighted_design(x, u, weights)
                total = out.sum() + f.sum() + w.sum() + s.sum() + gw.sum()
                torch.autograd.grad(total, [x, u], allow_unused=True)
        return form, run

    return [(first, plain),
            autograd(F64, f"float64 tensors with autograd ({shapes}; derivatives in x, u and p, as training takes "
                          "them)"),
            autograd(torch.float32, f"float32 tensors with autograd ({shapes}; training runs in float32)")]


def _verifier_forms(system, batch: _Batch) -> list[tuple[str, Callable[[], None]]]:
    from torch.nn.functional import linear

    from drlyap.enclosures import Affine, Dual, Interval, is_enclosure

    b, n, k = batch.size, system.n, system.k
    eye = torch.eye(n, dtype=F64).expand(b, n, n)
    kinds = {  # the verifier's states: at box centres, over boxes (intervals, affine forms), with gradients (duals)
        "intervals at points": lambda: Interval(batch.z, batch.z),
        "intervals over boxes": lambda: Interval(batch.lo, batch.hi),
        "affine forms": lambda: Affine.box(batch.lo, batch.hi),
        "dual numbers over intervals": lambda: Dual(Interval(batch.lo, batch.hi), Interval(eye, eye)),
        "dual numbers over affine forms": lambda: Dual(Affine.box(batch.lo, batch.hi), Affine.const(eye)),
    }
    shifts = Interval(torch.full((k,), -1e-6, dtype=F64), torch.full((k,), 1e-6, dtype=F64))

    def check(out, form: str) -> None:
        if not is_enclosure(out):
            raise ProbeFailure(form, problem=f"the dynamics returned a {type(out).__name__} on {form}: compute the "
                                             "output from x, u and p with torch operations (a tensor made anew, e.g. "
                                             "by torch.tensor or torch.zeros, drops the enclosure)")
        if tuple(out.shape) != (b, n):
            raise ProbeFailure(form, problem=f"the dynamics returned shape {tuple(out.shape)} on {form} for B = {b} "
                                             f"states, expected {(b, n)}")

    def states(make):
        z = make()
        return z, system.to_user(z), linear(z - batch.z, batch.gain) + batch.u

    def true_model(label: str, make) -> tuple[str, Callable[[], None]]:
        form = f"drlyap's verifier on {label}"

        def run() -> None:
            with torch.no_grad():
                z, x, u = states(make)
                check(system.true_dynamics(x, u, torch.zeros(k, dtype=F64)), form)
                if label in ("intervals over boxes", "dual numbers over intervals"):  # a box of shifts (robustness)
                    check(system.true_dynamics(x, u, shifts), form)
        return form, run

    def design_model(label: str, make) -> tuple[str, Callable[[], None]]:
        inner = "dual numbers" if label.startswith("dual") else label.removesuffix(" at points")
        form = f"drlyap's verifier on dual numbers in the parameters over {inner} (the design model's W = dF/dp)" \
            if system.perturbation is None else f"drlyap's verifier on {label} (the design model: F and the given W)"

        def run() -> None:
            with torch.no_grad():
                z, x, u = states(make)
                system.weighted_design(x, u, z * 0.0 + 1.0)
        return form, run

    return [true_model(label, make) for label, make in kinds.items()] + \
        [design_model(label, make) for label, make in kinds.items()]


class _Pair:
    """The checker's pair as far as the dynamics see it: the input, an affine function of the state."""

    def __init__(self, batch: _Batch) -> None:
        self.batch = batch

    def controller(self, z):
        return (z - self.batch.z).linear(self.batch.gain) + self.batch.u


def _checker_forms(system, batch: _Batch) -> list[tuple[str, Callable[[], None]]]:
    from drlyap.checker.affine import Af
    from drlyap.checker.arith import Du, Iv, _Ops
    from drlyap.checker.model import Residual

    b, n, k = batch.size, system.n, system.k
    kinds = {
        "intervals at points": lambda: Iv.point(batch.z),
        "intervals over boxes": lambda: Iv(batch.lo, batch.hi),
        "dual numbers": lambda: Du.seed(Iv(batch.lo, batch.hi), n, list(range(n))),
        "affine forms": lambda: Af.seed(batch.lo, batch.hi),
    }
    pair, zero = _Pair(batch), [[0.0] * k]
    boxed = {"name": "true", "xi_box": {"low": [[-1e-6] * k], "high": [[1e-6] * k]}}

    def form_of(label: str, claims: list[dict], form: str) -> tuple[str, Callable[[], None]]:
        def run() -> None:
            with torch.no_grad():
                z = kinds[label]()
                for claim in claims:
                    for out in Residual(claim, pair, system).fields(z):
                        if not isinstance(out, _Ops) or tuple(out.shape) != (b, n):
                            what = type(out).__name__ if not isinstance(out, _Ops) else f"shape {tuple(out.shape)}"
                            raise ProbeFailure(form, problem=f"the dynamics returned {what} on {form} for B = {b} "
                                                             f"states, expected an enclosure of shape {(b, n)}")
        return form, run

    forms = [form_of(label, [{"name": "true", "xi": zero}] + ([boxed] if label == "intervals over boxes" else []),
                     f"drlyap's checker on {label}") for label in kinds]
    if system.perturbation is None:  # the checker refuses a hand-given W on the design model (a ValueError of its own)
        forms += [form_of(label, [{"name": "plain", "model": "design", "xi": zero}],
                          f"drlyap's checker on dual numbers in the parameters over {label} (the design model's W)")
                  for label in kinds]
    return forms


# --------------------------------------------------------------------------------------------- the message
def _library_roots() -> tuple[str, ...]:
    roots = {str(Path(__file__).resolve().parents[1]), str(Path(torch.__file__).resolve().parent)}
    numpy = sys.modules.get("numpy")
    if numpy is not None and getattr(numpy, "__file__", None):
        roots.add(str(Path(numpy.__file__).resolve().parent))
    for name in ("stdlib", "platstdlib", "purelib", "platlib"):  # a package the dynamics call is not the user's line
        path = sysconfig.get_paths().get(name)
        if path:
            roots.add(str(Path(path).resolve()))
    return tuple(root + os.sep for root in roots)


def _dynamics_file(system) -> tuple[str | None, int | None]:
    fn = getattr(system.dynamics, "func", system.dynamics)  # a functools.partial's function
    code = getattr(fn, "__code__", None) or getattr(type(fn).__call__, "__code__", None)
    if code is None:
        return None, None
    name = code.co_filename
    return (name if name.startswith("<") else str(Path(name).resolve())), code.co_firstlineno


def _user_frame(err: BaseException, system) -> traceback.FrameSummary | None:
    """The deepest frame of ``err``'s traceback in the user's code (outside drlyap, torch, numpy, the standard library
    and installed packages), else the deepest in the dynamics' own file; None if neither is there."""
    frames = traceback.extract_tb(err.__traceback__)
    roots = _library_roots()

    def path(f: traceback.FrameSummary) -> str:
        return str(Path(f.filename).resolve()) if not f.filename.startswith("<") else f.filename

    user = [f for f in frames if not f.filename.startswith("<") and not path(f).startswith(roots)]  # "<string>": exec
    if user:
        return user[-1]
    source, _ = _dynamics_file(system)
    same = [f for f in frames if source is not None and path(f) == source]
    return same[-1] if same else None


def _shown(path: str) -> str:
    """``path`` relative to the working directory where it lies below it, else as it is."""
    if path.startswith("<"):
        return path
    try:
        rel = os.path.relpath(path)
    except ValueError:
        return path
    return rel if not rel.startswith("..") else path


def _where(err: BaseException | None, system) -> tuple[str, str]:
    """``file:line`` of the failure (or of the dynamics' definition) and the source line, if known."""
    frame = _user_frame(err, system) if err is not None else None
    if frame is not None:
        return f"{_shown(frame.filename)}:{frame.lineno}", (frame.line or "").strip()
    source, line = _dynamics_file(system)
    if source is not None:
        return f"{_shown(source)}:{line} (the dynamics)", ""
    return f"the dynamics {system.dynamics!r}", ""


def _as_written(name: str, line: str) -> str:
    """``name`` as the source line writes it: ``torch.abs``, ``.abs()``, or the bare name."""
    base = name.strip("_").removeprefix("r") if name.startswith("__r") else name.strip("_")
    for prefix in ("torch.nn.functional.", "torch.linalg.", "torch.", "F."):
        if f"{prefix}{base}(" in line:
            return f"{prefix}{base}"
    if f".{base}(" in line:
        return f".{base}()"
    return {"matmul": "@ (matrix product)", "setitem": "item assignment (x[...] = ...)"}.get(base, base)


def _operation(err: BaseException, line: str, form: str) -> str:
    """A sentence naming the unsupported operation, when the error or the line says which; else ""."""
    msg = str(err)
    call = re.search(r"\b(np|numpy)\.(\w+)\s*\(", line)
    if call:
        return (f"{call.group(1)}.{call.group(2)} is a numpy function: numpy functions cannot run on tensors that carry "
                f"gradients (training) nor on drlyap's enclosures (the verifier's, the checker's); use "
                f"torch.{call.group(2)}")
    if "numpy" in msg.lower():
        return ("numpy ran on x, u or p (a numpy function or .numpy()): numpy cannot run on tensors that carry gradients "
                "(training) nor on drlyap's enclosures (the verifier's, the checker's); use the torch functions")
    call = re.search(r"\bmath\.(\w+)\s*\(", line)
    if call:
        return (f"math.{call.group(1)} takes single Python numbers, not batches of states nor drlyap's enclosures; use "
                f"torch.{call.group(1)}")
    if "is ambiguous" in msg or ("Boolean value" in msg and "Tensor" in msg):
        return (f"a Python `if` (or and/or/not) on a tensor fails on {form}: the dynamics run on batches of states and "
                "on enclosures, which have no single truth value; write F as one formula of x, u and p")
    if "float32" in form and re.search(r"dtype|Double|Float|float != double", msg):
        return ("a float64 constant meets the float32 tensors training runs on; make constants with dtype=x.dtype "
                "(and device=x.device)")
    found = re.search(r"does not support (\S+?)[;:,]? (?:use|:)", msg) or re.search(r"does not support ([\w.]+)", msg)
    if found:
        name = found.group(1)
        shown = _as_written(name, line)
        hint = ""
        if name.strip("_") in ("zeros_like", "ones_like", "empty_like", "full_like", "zeros", "ones", "empty", "full",
                               "setitem", "tensor", "as_tensor", "index_put_", "copy_"):
            hint = "; build the output with torch.stack([...], dim=-1) instead of writing into a tensor"
        elif "matmul" in name or name in ("mm", "bmm", "mv", "einsum", "linear"):
            hint = "; write the products out entry by entry (x[:, 0] * a + x[:, 1] * b)"
        elif name in ("where", "maximum", "minimum", "clamp", "clip", "relu", "sign", "heaviside", "max", "min"):
            hint = "; no branches or kinks: write F as one smooth formula"
        return f"{shown} is not supported by {form}{hint}"
    found = re.search(r"^(\w+) is not differentiable", msg)
    if found:
        shown = _as_written(found.group(1), line)
        return f"{shown} is not supported by {form} (they bound derivatives, and {shown} has a kink)"
    found = re.search(r"'([<>=!]+)' not supported between instances of '(\w+)'", msg)
    if found and found.group(2) in _ENCLOSURE_NAMES:
        return (f"the comparison {found.group(1)} is not supported by {form} (sets of values, with no single truth "
                "value): no `if`, torch.where or masks on x, u or p; write F as one smooth formula")
    found = re.search(r"'(\w+)' object has no attribute '(\w+)'", msg)
    if found and found.group(1) in _ENCLOSURE_NAMES:
        attr = found.group(2)
        hint = ""
        if attr in ("item", "tolist", "numpy", "float", "double", "to", "type", "detach", "cpu", "cuda", "half"):
            hint = ": the dynamics must take no numbers out of x, u, p and change no dtype"
        elif attr in ("clone", "copy_", "fill_", "zero_", "add_", "mul_", "sub_", "div_", "clamp_", "abs_"):
            hint = ": no copies or in-place operations; compute new values (v = -friction * v)"
        return f".{attr} is not supported by {form}{hint}"
    found = re.search(r"unsupported operand type\(s\) for (\S+): '(\w+)' and '(\w+)'", msg)
    if found and (found.group(2) in _ENCLOSURE_NAMES or found.group(3) in _ENCLOSURE_NAMES):
        hint = "; write the products out entry by entry (x[:, 0] * a + x[:, 1] * b)" if found.group(1) == "@" else ""
        return f"the operator {found.group(1)} is not supported by {form}{hint}"
    if "sum over all axes" in msg or "summing over axis 0" in msg:
        return (f"a sum over the batch (x.sum() without dim, or over dim 0) is not supported by {form}: it mixes the "
                "states of a batch; sum over the coordinates only (dim=-1)")
    found = re.search(r"powers by non-negative integers only, got (.+)$", msg)
    if found:
        return (f"the power ** {found.group(1)} is not supported by {form}: only ** by a non-negative integer "
                "(torch.sqrt for ** 0.5, 1 / x for ** -1)")
    if re.search(r"(float|int)\(\) argument must be|must be real number, not|only one element tensors", msg):
        return (f"float()/int()/.item() fails on {form}: it takes one number out of a tensor, and the dynamics run on "
                "batches of states and on enclosures; keep every value a tensor")
    if "appears to not have been used in the graph" in msg:
        return ("the dynamics do not depend on p through autograd (training differentiates F in the parameters): a "
                "value of p was taken out of the graph (float(), .item(), .detach(), numpy, torch.tensor(...) of "
                "entries), or F does not use p")
    return ""


def failure_error(system, failure: ProbeFailure) -> ValueError:
    """The one-line ValueError of a failed form: where, what, the exception, the line of code, the form."""
    err = failure.error
    where, line = _where(err, system)
    if failure.problem:
        what = failure.problem
    else:
        op = _operation(err, line, failure.form)
        raised = f"{type(err).__name__}: {' '.join(str(err).split())}"
        what = f"{op}. {raised}" if op else f"the dynamics raised {raised} on {failure.form}"
    code = f" In: `{line}`." if line else ""
    end = "" if what.endswith(".") else "."
    return ValueError(f"{where}: {what}{end}{code} (system {system.name!r}, checked when loaded, before any training "
                      "or proof)")


def dynamics_error(system, err: Exception, form: str) -> ValueError:
    """The one-line ValueError of an exception the user's dynamics raised on ``form`` (e.g. at x* when the system is
    built)."""
    return failure_error(system, ProbeFailure(form, err))
