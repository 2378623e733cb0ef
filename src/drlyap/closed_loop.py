"""The closed loop: a system, its controller pi and its Lyapunov function V, the object every proof, check and simulation
is about.

A :class:`ClosedLoop` carries the three together, with

* its right-hand side ``zdot = F(x* + z, pi(z), p0 + E xi)`` on the true model, or ``f + W xi`` on the design
  model (:meth:`ClosedLoop.rhs`), and its Jacobian (:meth:`ClosedLoop.jacobian`, the one point-Jacobian routine,
  :func:`jacobian`);
* the residual of a decrease condition of :mod:`drlyap.conditions` (:meth:`ClosedLoop.residual`), and
  :meth:`ClosedLoop.exact`: the residual with the networks read in float64 (or another dtype), without gradients,
  the arithmetic the verifier's claims are about; the float64 copy of the networks is made once per loop
  (:meth:`ClosedLoop.in_dtype`).

States are local coordinates ``z = x - x*`` (angles wrapped), batched on the first axis. The verifier runs the
networks' and the system's own code on enclosures through the same object (``loop.lyapunov``,
``loop.controller``), so the loop is also the thing that is bounded. A loop's networks must not change once a
copy of them was taken (train first, then build the loop that is proved).
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch
from torch import Tensor, nn

from drlyap.kinds import Model
from drlyap.systems import UncertainSystem

F64 = torch.float64


def jacobian(fn: Callable[[Tensor], Tensor], x: Tensor) -> tuple[Tensor, Tensor]:
    """``fn(x) (B, m)`` and its Jacobian ``(B, m, a)`` at ``x (B, a)`` (batched: row by row, one reverse pass
    each; the rows of different batch entries do not mix)."""
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        f = fn(x)
        rows = [torch.autograd.grad(f[:, i].sum(), x, retain_graph=True)[0] for i in range(f.shape[1])]
    return f.detach(), torch.stack(rows, dim=1)


class ClosedLoop:
    """``(system, lyapunov, controller)``: the closed loop ``zdot = F(x* + z, pi(z))`` with its Lyapunov function V.

    ``lyapunov``: V with ``value_and_grad`` (:class:`~drlyap.networks.Lyapunov` or a quadratic one);
    ``controller``: pi on local states (:class:`~drlyap.networks.Controller`, a linear one, ...).
    """

    def __init__(self, system: UncertainSystem, lyapunov: nn.Module, controller: nn.Module) -> None:
        self.system, self.lyapunov, self.controller = system, lyapunov, controller
        self._copies: dict[torch.dtype, ClosedLoop] = {}

    def __repr__(self) -> str:
        return f"ClosedLoop({self.system.name}, {type(self.lyapunov).__name__}, {type(self.controller).__name__})"

    @property
    def n(self) -> int:
        """State dimension."""
        return self.system.n

    def with_lyapunov(self, lyapunov: nn.Module) -> ClosedLoop:
        """The same system and controller with another Lyapunov function (e.g. a quadratic ``z^T P z``)."""
        return ClosedLoop(self.system, lyapunov, self.controller)

    # ------------------------------------------------------------------ copies
    def in_dtype(self, dtype: torch.dtype = F64) -> ClosedLoop:
        """The same loop with copies of the networks in ``dtype`` and no gradients, made once per dtype."""
        if dtype not in self._copies:
            lyap, ctrl = copy.deepcopy(self.lyapunov).to(dtype), copy.deepcopy(self.controller).to(dtype)
            for p in [*lyap.parameters(), *ctrl.parameters()]:
                p.requires_grad_(False)
            self._copies[dtype] = ClosedLoop(self.system, lyap, ctrl)
        return self._copies[dtype]

    @property
    def f64(self) -> ClosedLoop:
        """:meth:`in_dtype` float64: the arithmetic every claim of the verifier is about."""
        return self.in_dtype(F64)

    # ------------------------------------------------------------------ the field
    def rhs(self, z: Tensor, xi: Tensor | None = None, model: str = "true") -> Tensor:
        """``zdot (B, n)`` at local states ``z (B, n)``: the true model ``F(x, pi(z), p0 + E xi)`` (``xi`` ``(k,)``
        or ``(B, k)``; None: nominal), or with ``model="design"`` the design model ``f + W xi``."""
        x, u = self.system.to_user(z), self.controller(z)
        if model == Model.TRUE:
            return self.system.true_dynamics(x, u, xi)
        if model != Model.DESIGN:
            raise ValueError(f"unknown model {model!r}; valid: design, true")
        f, w = self.system.design_model(x, u)
        if xi is None:
            return f
        xi = torch.as_tensor(xi, dtype=f.dtype, device=f.device)
        return f + (w * xi.reshape(-1, 1, w.shape[-1])).sum(-1)

    def jacobian(self, z: Tensor, xi: Tensor | None = None, model: str = "true") -> tuple[Tensor, Tensor]:
        """``zdot (B, n)`` and the closed-loop Jacobian ``d zdot / dz (B, n, n)`` at local states ``z (B, n)``."""
        return jacobian(lambda s: self.rhs(s, xi, model), z)

    # ------------------------------------------------------------------ conditions
    def value(self, z: Tensor, chunk: int = 20000) -> Tensor:
        """``V (B,)`` at local states ``z (B, n)``, chunked, without gradients (in the networks' dtype)."""
        ref = next(iter([*self.lyapunov.parameters(), *self.lyapunov.buffers()]))
        with torch.no_grad():
            return torch.cat([self.lyapunov(z[i:i + chunk].to(ref)) for i in range(0, z.shape[0], chunk)])

    def residual(self, condition, z) -> Tensor:
        """``condition``'s residual ``(B,)`` at local states ``z (B, n)`` (a tensor, differentiable, or an
        enclosure): the condition holds at a state iff its entry is ``<= 0``."""
        return condition.residual(condition.terms(self, z))

    def exact(self, condition, z: Tensor, dtype: torch.dtype = F64) -> Tensor:
        """The residual at local states ``z (B, n)`` by the ordinary torch code path, networks and states in
        ``dtype`` (float64 by default), without gradients."""
        loop = self.in_dtype(dtype)
        with torch.no_grad():
            return loop.residual(condition, torch.as_tensor(z).to(dtype))
