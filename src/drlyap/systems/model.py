"""Uncertain control-affine systems, declared once by their true parametric dynamics.

A system is written as ``xdot = F(x, u, p)`` with physical parameters ``p``. Some of them are
uncertain: the uncertainty ``xi`` is the deviation of those parameters from their nominal values,
so the *true model* at a shift ``xi`` is ``F(x, u, p0 + E xi)`` (``E`` picks the uncertain
entries). The *design model* of the paper is the first-order expansion at ``p0``::

    xdot = f(x, u) + W(x, u) xi,   f = F(., ., p0),   W = dF/dp_uncertain at p0,

derived here by autodiff, so the dynamics are written once. A user may also hand ``W`` in.

Coordinates: users see states in their own coordinates ``x``. Networks, losses and the verifier
work in *local* coordinates ``z = x - x*`` with angle coordinates wrapped into ``[-pi, pi)``.

:class:`UncertainSystem` is the system, :class:`SystemDefaults` its typed training and proof defaults.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from drlyap.config import SystemDefaults
from drlyap.systems.probe import dynamics_error, probe_system

if TYPE_CHECKING:  # the enclosures load where a system is bounded, not where it is only described or run
    from drlyap.enclosures import Interval

Dynamics = Callable[[Tensor, Tensor, Tensor], Tensor]
"""``F(x (B, n), u (B, m), p (B, P)) -> xdot (B, n)``, batched, written with torch ops."""

Perturbation = Callable[[Tensor, Tensor], Tensor]
"""``W(x (B, n), u (B, m)) -> (B, n, k)``: a hand-given design-model perturbation matrix."""

XiSampler = Callable[[int, torch.Generator], Tensor]
"""``sample(N, generator) -> (N, k)``: draws training samples of the uncertainty."""


def _finite(values: Sequence[float], what: str, names: Sequence[str]) -> tuple[float, ...]:
    """``values`` as a tuple of finite floats, or an error naming the bad entries."""
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} must be a sequence of numbers, got {values!r}") from err
    bad = [f"{names[i] if i < len(names) else i}={v}" for i, v in enumerate(out) if not math.isfinite(v)]
    if bad:
        raise ValueError(f"{what} must be finite, got {', '.join(bad)}")
    return out


def _as_pair(box: Sequence[Sequence[float]], what: str, dim: int | None = None) -> tuple[tuple[float, ...], tuple[float, ...]]:
    try:
        low, high = (tuple(float(v) for v in side) for side in box)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} must be a pair (low, high) of number sequences, got {box!r}") from err
    if len(low) != len(high) or (dim is not None and len(low) != dim):
        raise ValueError(f"{what} needs low and high of length {dim or len(low)}, got {len(low)} and {len(high)}")
    for i, (lo, hi) in enumerate(zip(low, high)):
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"{what} has a non-finite bound in coordinate {i}: [{lo}, {hi}]")
        if not lo < hi:
            raise ValueError(f"{what} is empty or inverted in coordinate {i}: low {lo} must be < high {hi}")
    return low, high


@dataclass(frozen=True)
class UncertainSystem:
    """An uncertain control-affine system ``xdot = F(x, u, p)``.

    Attributes:
        name: registry name (``pendulum``).
        state_names, input_names: one label per coordinate (used in plots and errors).
        param_names, nominal_params: all physical parameters ``p0`` in the order ``dynamics`` unpacks.
        uncertain: names of the uncertain parameters; ``xi`` is ordered the same way.
        dynamics: the true model ``F`` (see :data:`Dynamics`).
        state_box: ``(low, high)`` of the region X in user coordinates.
        input_box: ``(low, high)`` of the input set U.
        equilibrium: ``x*`` in user coordinates; ``equilibrium_input`` is ``u*`` (``F(x*, u*, p) = 0``).
        angle_dims: indices of angle coordinates (wrapped into ``[x*_i - pi, x*_i + pi)``).
        test_box: region the paper draws evaluation initial states from (defaults to ``state_box``).
        perturbation: optional hand-given ``W``; by default ``W`` is derived by autodiff.
        xi_sampler: the training distribution of ``xi`` used by ``reproduce``.
        test_xi: the paper's out-of-distribution test shift.
        reference_states: start states (user coordinates, each of length n) of the paper-like figures
            (``reproduce``'s certificate/input plot, ``compare``'s figures); empty: states drawn from the test box.
        rl_timing: ``(dt, episode_time)`` of the RL environment (default ``(sim_dt, horizon)``).
        rl_reward_weights: ``(state (n,), input (m,))`` diagonal weights of the RL cost
            ``-(sum w_i z_i^2 + sum w_j (u_j - u*_j)^2)``; default: 1/half-width^2 of the boxes (inputs x 0.001).
        defaults: the system's training and proof defaults (:class:`SystemDefaults`, or a dict of its fields).
        sim_dt, horizon: integration step and simulated time (system time units) for evaluation.
        success_tol: a trajectory succeeds when, over the last ``settle_fraction`` of the horizon, every
            coordinate of ``x - x*`` (angles wrapped) stays within ``success_tol`` times the box half-width.
        state_units, input_units: one unit per coordinate (``("rad", "rad/s")``), or empty when unknown;
            used on plot axes (``theta [rad]``).
        time_unit: unit of time in ``dynamics`` (``s``; ``step`` for a model in time steps).
        plot_dims: the two state coordinates of phase portraits and V/decrease maps (default the first two);
            with more than two states these are slices through x* (other coordinates at x*).
    """

    name: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    param_names: tuple[str, ...]
    nominal_params: tuple[float, ...]
    uncertain: tuple[str, ...]
    dynamics: Dynamics
    state_box: tuple[tuple[float, ...], tuple[float, ...]]
    input_box: tuple[tuple[float, ...], tuple[float, ...]]
    equilibrium: tuple[float, ...]
    equilibrium_input: tuple[float, ...] | None = None
    angle_dims: tuple[int, ...] = ()
    test_box: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    perturbation: Perturbation | None = None
    xi_sampler: XiSampler | None = None
    test_xi: tuple[float, ...] | None = None
    reference_states: tuple[tuple[float, ...], ...] = ()
    rl_timing: tuple[float, float] | None = None
    rl_reward_weights: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    defaults: SystemDefaults = field(default_factory=SystemDefaults)
    sim_dt: float = 0.01
    horizon: float = 20.0
    success_tol: float = 0.02
    settle_fraction: float = 0.1
    description: str = ""
    state_units: tuple[str, ...] = ()
    input_units: tuple[str, ...] = ()
    time_unit: str = "s"
    plot_dims: tuple[int, int] = (0, 1)

    def __post_init__(self) -> None:
        """Normalise the user's fields to tuples of floats and refuse a system the rest of drlyap cannot use: each
        check names the bad field and what would be valid, in the order the fields are checked here."""
        self._normalise_labels()
        self._normalise_boxes_and_values()
        self._normalise_rl()
        self._check_equilibrium()
        self._check_coordinates()
        self._check_dynamics_at_equilibrium()
        if self.xi_sampler is not None:
            self._check_sampler()

    def _normalise_labels(self) -> None:
        """The defaults as :class:`SystemDefaults`; the units, one string per coordinate or none; the time unit."""
        n, m = len(self.state_names), len(self.input_names)
        set_ = object.__setattr__
        set_(self, "defaults", SystemDefaults.of(self.defaults, f"{self.name}: defaults"))
        for what, units, dim in (("state_units", self.state_units, n), ("input_units", self.input_units, m)):
            if isinstance(units, str) or not all(isinstance(u, str) for u in units) or len(units) not in (0, dim):
                raise ValueError(f"{self.name}: {what} must be empty or {dim} strings (one per coordinate), "
                                 f"got {units!r}")
            set_(self, what, tuple(units))
        if not isinstance(self.time_unit, str):
            raise ValueError(f"{self.name}: time_unit must be a string such as 's', got {self.time_unit!r}")

    def _normalise_boxes_and_values(self) -> None:
        """The boxes as ``(low, high)`` pairs of the right length; parameters, equilibrium, test shift and reference
        states as finite floats."""
        n = len(self.state_names)
        set_ = object.__setattr__
        set_(self, "state_box", _as_pair(self.state_box, f"{self.name}: state_box", n))
        set_(self, "input_box", _as_pair(self.input_box, f"{self.name}: input_box", len(self.input_names)))
        set_(self, "test_box", _as_pair(self.test_box or self.state_box, f"{self.name}: test_box", n))
        if len(self.nominal_params) != len(self.param_names):
            raise ValueError(f"{self.name}: {len(self.param_names)} parameter names but "
                             f"{len(self.nominal_params)} nominal values")
        set_(self, "nominal_params", _finite(self.nominal_params, f"{self.name}: nominal_params", self.param_names))
        set_(self, "equilibrium", _finite(self.equilibrium, f"{self.name}: equilibrium", self.state_names))
        if self.equilibrium_input is not None:
            set_(self, "equilibrium_input", _finite(self.equilibrium_input, f"{self.name}: equilibrium_input",
                                                    self.input_names))
        if self.test_xi is not None:
            set_(self, "test_xi", _finite(self.test_xi, f"{self.name}: test_xi", self.uncertain))
        set_(self, "reference_states", self._reference_states())

    def _reference_states(self) -> tuple[tuple[float, ...], ...]:
        """``reference_states`` as finite states of length n."""
        n = len(self.state_names)
        try:
            refs = tuple(_finite(r, f"{self.name}: reference_states[{i}]", self.state_names)
                         for i, r in enumerate(self.reference_states))
        except TypeError as err:
            raise ValueError(f"{self.name}: reference_states must be a sequence of states of length {n}, "
                             f"got {self.reference_states!r}") from err
        for i, r in enumerate(refs):
            if len(r) != n:
                raise ValueError(f"{self.name}: reference_states[{i}] has {len(r)} entries, state has {n} "
                                 f"({', '.join(self.state_names)})")
        return refs

    def _normalise_rl(self) -> None:
        """The RL environment's timing ``(dt, episode_time)`` and reward weights, where given."""
        n, m = len(self.state_names), len(self.input_names)
        set_ = object.__setattr__
        if self.rl_timing is not None:
            timing = _finite(self.rl_timing, f"{self.name}: rl_timing", ("dt", "episode_time"))
            if len(timing) != 2 or not 0 < timing[0] <= timing[1]:
                raise ValueError(f"{self.name}: rl_timing must be (dt, episode_time) with 0 < dt <= episode_time, "
                                 f"got {self.rl_timing}")
            set_(self, "rl_timing", timing)
        if self.rl_reward_weights is not None:
            try:
                wx, wu = self.rl_reward_weights
            except (TypeError, ValueError) as err:
                raise ValueError(f"{self.name}: rl_reward_weights must be (state weights, input weights)") from err
            wx = _finite(wx, f"{self.name}: rl_reward_weights[0]", self.state_names)
            wu = _finite(wu, f"{self.name}: rl_reward_weights[1]", self.input_names)
            if len(wx) != n or len(wu) != m or min(wx + wu) < 0:
                raise ValueError(f"{self.name}: rl_reward_weights needs {n} state and {m} input weights >= 0, "
                                 f"got {self.rl_reward_weights}")
            set_(self, "rl_reward_weights", (wx, wu))

    def _check_equilibrium(self) -> None:
        """The uncertain parameters among the parameters; ``x*`` and ``u*`` (0 by default) of the right length and
        strictly inside the state and input boxes."""
        n, m = len(self.state_names), len(self.input_names)
        unknown = [u for u in self.uncertain if u not in self.param_names]
        if unknown or not self.uncertain:
            raise ValueError(f"{self.name}: uncertain parameters {unknown or '()'} must be a non-empty "
                             f"subset of {self.param_names}")
        if len(self.equilibrium) != n:
            raise ValueError(f"{self.name}: equilibrium has {len(self.equilibrium)} entries, state has {n}")
        u_star = self.equilibrium_input if self.equilibrium_input is not None else (0.0,) * m
        if len(u_star) != m:
            raise ValueError(f"{self.name}: equilibrium_input has {len(u_star)} entries, input has {m}")
        object.__setattr__(self, "equilibrium_input", tuple(float(v) for v in u_star))
        lo, hi = self.input_box
        if not all(a < b < c for a, b, c in zip(lo, u_star, hi)):
            raise ValueError(f"{self.name}: equilibrium input {u_star} must lie strictly inside U = [{lo}, {hi}]")
        slo, shi = self.state_box
        if not all(a < b < c for a, b, c in zip(slo, self.equilibrium, shi)):
            raise ValueError(f"{self.name}: equilibrium {self.equilibrium} must lie strictly inside X")

    def _check_coordinates(self) -> None:
        """Angle and plot coordinates that index the state; a test shift with one value per uncertain parameter."""
        n = len(self.state_names)
        if any(not 0 <= d < n for d in self.angle_dims):
            raise ValueError(f"{self.name}: angle_dims {self.angle_dims} must index state coordinates 0..{n - 1}")
        dims = tuple(self.plot_dims)
        if n >= 2 and (len(dims) != 2 or dims[0] == dims[1] or any(not (isinstance(d, int) and 0 <= d < n) for d in dims)):
            raise ValueError(f"{self.name}: plot_dims {self.plot_dims} must be two different state coordinates "
                             f"0..{n - 1}")
        object.__setattr__(self, "plot_dims", dims)
        if self.test_xi is not None and len(self.test_xi) != self.k:
            raise ValueError(f"{self.name}: test_xi needs {self.k} values ({', '.join(self.uncertain)})")

    def _check_dynamics_at_equilibrium(self) -> None:
        """The user's dynamics (and perturbation W, where given) run at ``(x*, u*)`` with the shapes asked, and
        ``F(x*, u*, p0) = 0``."""
        n, u_star = len(self.state_names), self.equilibrium_input
        x_star = torch.tensor([self.equilibrium], dtype=torch.float64)
        try:
            residual = self.true_dynamics(x_star, torch.tensor([u_star], dtype=torch.float64))
        except Exception as err:  # noqa: BLE001 - the user's code: named by file and line, whatever it raised
            raise dynamics_error(self, err, f"float64 tensors at x* = {list(self.equilibrium)}, u* = {list(u_star)} "
                                            "(B = 1)") from None
        if not isinstance(residual, Tensor) or tuple(residual.shape) != (1, n):
            got = tuple(residual.shape) if isinstance(residual, Tensor) else f"a {type(residual).__name__}"
            raise ValueError(f"{self.name}: dynamics must return shape (B, {n}) for B states, got {got} for B = 1")
        if self.perturbation is not None:
            self._check_perturbation(x_star)
        if not torch.isfinite(residual).all() or residual.abs().max() > 1e-9:
            raise ValueError(f"{self.name}: F(x*, u*, p0) = {residual.tolist()[0]} is not zero; "
                             "the equilibrium must be an equilibrium of the nominal system")

    def _check_perturbation(self, x_star: Tensor) -> None:
        """The hand-given W runs at ``(x*, u*)`` (``x_star (1, n)``) and returns shape ``(1, n, k)``."""
        n = len(self.state_names)
        try:
            w = self.perturbation(x_star, torch.tensor([self.equilibrium_input], dtype=torch.float64))
        except Exception as err:  # noqa: BLE001 - as the dynamics' above
            raise dynamics_error(self, err, f"the perturbation W at x* = {list(self.equilibrium)} (B = 1)") from None
        if not isinstance(w, Tensor) or tuple(w.shape) != (1, n, self.k):
            got = tuple(w.shape) if isinstance(w, Tensor) else f"a {type(w).__name__}"
            raise ValueError(f"{self.name}: perturbation must return shape (B, {n}, {self.k}), got {got}")

    def _check_sampler(self, count: int = 4) -> None:
        """Call ``xi_sampler`` once with a seeded generator: it must give ``count`` finite rows of width k."""
        try:
            draw = torch.as_tensor(self.xi_sampler(count, torch.Generator().manual_seed(0)))
        except Exception as err:
            raise ValueError(f"{self.name}: xi_sampler({count}, generator) failed: {err!r}") from err
        shape = tuple(draw.shape)
        if shape != (count, self.k) and not (self.k == 1 and shape == (count,)):
            raise ValueError(f"{self.name}: xi_sampler(N, generator) must return shape (N, {self.k}) (one column per "
                             f"uncertain parameter: {', '.join(self.uncertain)}), got {shape} for N = {count}")
        if not torch.isfinite(draw.to(torch.float64)).all():
            raise ValueError(f"{self.name}: xi_sampler returned non-finite values {draw.tolist()}")

    # ----------------------------------------------------------------- dimensions
    @property
    def n(self) -> int:
        """State dimension."""
        return len(self.state_names)

    @property
    def m(self) -> int:
        """Input dimension."""
        return len(self.input_names)

    @property
    def k(self) -> int:
        """Number of uncertain parameters (length of ``xi``)."""
        return len(self.uncertain)

    def _tensor(self, values: Sequence[float], like: Tensor) -> Tensor:
        """``values`` (a tuple of the system's) as a constant tensor of ``like``'s dtype and device, made once per
        dtype and device (simulation calls this at every step). Callers must not write into it."""
        key = (values, like.dtype, like.device)
        cached = self.__dict__.get("_constants")
        if cached is None:
            cached = {}
            object.__setattr__(self, "_constants", cached)
        out = cached.get(key)
        if out is None:
            out = cached[key] = torch.as_tensor(values, dtype=like.dtype, device=like.device)
        return out

    @property
    def uncertain_index(self) -> list[int]:
        return [self.param_names.index(u) for u in self.uncertain]

    # ----------------------------------------------------------------- coordinates
    def with_state_box(self, box) -> UncertainSystem:
        """The same system on another state box ``(low, high)`` in user coordinates (a training box), checked as a
        system's own box is: a ValueError (or TypeError) for a malformed box or one that does not hold x* strictly
        inside. The system itself is untouched."""
        return replace(self, state_box=tuple(tuple(float(v) for v in side) for side in box))

    def local_box(self) -> tuple[Tensor, Tensor]:
        """The region X in local coordinates, ``(low (n,), high (n,))`` in float64."""
        lo, hi = (torch.tensor(b, dtype=torch.float64) for b in self.state_box)
        x_star = torch.tensor(self.equilibrium, dtype=torch.float64)
        return lo - x_star, hi - x_star

    def to_local(self, x: Tensor) -> Tensor:
        """User coordinates ``x (B, n)`` to local ``z = x - x*`` with angles wrapped into [-pi, pi)."""
        z = x - self._tensor(self.equilibrium, x)
        if self.angle_dims:
            idx = list(self.angle_dims)
            z = z.clone()
            z[:, idx] = torch.remainder(z[:, idx] + math.pi, 2 * math.pi) - math.pi
        return z

    def to_user(self, z: Tensor) -> Tensor:
        """Local ``z (B, n)`` back to user coordinates."""
        return z + self._tensor(self.equilibrium, z)

    # ----------------------------------------------------------------- parameters
    def params(self, xi: Tensor | Interval | None, like: Tensor) -> Tensor:
        """Physical parameters ``p0 + E xi`` as ``(B, P)``; ``xi`` is ``(k,)`` or ``(B, k)``.

        On enclosures (``like`` an :class:`~drlyap.enclosures.Interval` or ``Dual``) the result is an exact
        enclosure of ``p0 + E xi`` of the same level; ``xi`` may then also be an interval box ``(k,)``.
        """
        if _enclosed(like):
            return self._param_enclosure(xi, like)
        p = self._tensor(self.nominal_params, like).expand(like.shape[0], -1).clone()
        if xi is not None:
            xi = torch.as_tensor(xi, dtype=like.dtype, device=like.device)
            p[:, self.uncertain_index] = p[:, self.uncertain_index] + xi
        return p

    def _param_enclosure(self, xi: Tensor | Interval | None, like) -> Interval:
        from drlyap.enclosures import Interval, lift

        p = torch.tensor(self.nominal_params, dtype=torch.float64, device=like.device).expand(like.shape[0], -1)
        lo, hi = p.clone(), p.clone()
        if xi is not None:
            idx = self.uncertain_index
            box = xi if isinstance(xi, Interval) else Interval.const(xi)
            lo[:, idx] = (Interval.const(p[:, idx]) + box.lo).lo
            hi[:, idx] = (Interval.const(p[:, idx]) + box.hi).hi
        return lift(Interval(lo, hi), like.level)

    def check_xi(self, xi: Sequence[float] | Tensor) -> Tensor:
        """Validate a parameter shift and return it as a float64 ``(k,)`` tensor."""
        t = torch.as_tensor(xi, dtype=torch.float64).reshape(-1)
        if t.numel() != self.k:
            raise ValueError(f"{self.name} takes {self.k} xi value(s) ({', '.join(self.uncertain)}), got {t.numel()}")
        if not torch.isfinite(t).all():
            raise ValueError(f"xi must be finite, got {t.tolist()}")
        return t

    # ----------------------------------------------------------------- models
    def true_dynamics(self, x: Tensor, u: Tensor, xi: Tensor | None = None) -> Tensor:
        """True model ``F(x, u, p0 + E xi)``: ``x (B, n)``, ``u (B, m)``, ``xi`` ``(k,)`` or ``(B, k)`` -> ``(B, n)``."""
        return self.dynamics(x, u, self.params(xi, x))

    def check_finite(self, xi_samples: Tensor | None = None, states: Tensor | None = None, count: int = 4096,
                     seed: int = 0) -> None:
        """A ValueError naming the system and the first state at which the true model is not finite (NaN or inf).

        Evaluated before any training or proof, on ``states (S, n)`` (user coordinates, e.g. a training grid),
        the box's corners and ``count`` states drawn uniformly from the state box, with inputs drawn uniformly
        from U, at the nominal parameters and at the rows of ``xi_samples (N, k)`` (cycled over the states):
        dynamics that are not finite on the box would otherwise surface as errors deep inside linear algebra.

        First, once per system (:func:`~drlyap.systems.probe.probe_system`): one small batch through everything that
        will run the dynamics (tensors with autograd, the verifier's enclosures, the checker's arithmetic), so that
        an operation training or a proof cannot take is named, with its file and line, before any training."""
        probe_system(self)
        gen = torch.Generator().manual_seed(seed)
        lo, hi = (torch.tensor(b, dtype=torch.float64) for b in self.state_box)
        ulo, uhi = (torch.tensor(b, dtype=torch.float64) for b in self.input_box)
        corners = torch.cartesian_prod(*[torch.stack([lo[i], hi[i]]) for i in range(self.n)]).reshape(-1, self.n)
        drawn = lo + (hi - lo) * torch.rand(count, self.n, generator=gen, dtype=torch.float64)
        given = torch.zeros(0, self.n, dtype=torch.float64) if states is None else states.detach().double().cpu()
        x = torch.cat([given, corners[:count], drawn])
        u = ulo + (uhi - ulo) * torch.rand(x.shape[0], self.m, generator=gen, dtype=torch.float64)
        shifts: list[Tensor | None] = [None]
        if xi_samples is not None and len(xi_samples):
            xi = torch.as_tensor(xi_samples, dtype=torch.float64).reshape(-1, self.k)
            shifts.append(xi[torch.arange(x.shape[0]) % xi.shape[0]])
        for xi in shifts:
            with torch.no_grad():
                f = self.true_dynamics(x, u, xi)
            bad = ~torch.isfinite(f).all(-1)
            if bool(bad.any()):
                i = int(bad.nonzero()[0, 0])
                at = "" if xi is None else f", xi = {[round(float(v), 6) for v in xi[i]]}"
                raise ValueError(f"{self.name}: the dynamics are not finite ({[float(v) for v in f[i]]}) at "
                                 f"x = {[round(float(v), 6) for v in x[i]]}, u = {[round(float(v), 6) for v in u[i]]}"
                                 f"{at}; F must be finite on the whole state box and input set")

    def design_model(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """Design model terms ``f (B, n)`` and ``W (B, n, k)`` at ``x (B, n)``, ``u (B, m)``.

        Differentiable with respect to ``x`` and ``u`` (for training through the controller).
        """
        if self.perturbation is not None:
            return self.true_dynamics(x, u), self.perturbation(x, u)
        graph = torch.is_grad_enabled()
        p = self.params(None, x).requires_grad_(True)
        with torch.enable_grad():
            f = self.dynamics(x, u, p)
            rows = [torch.autograd.grad(f[:, i].sum(), p, create_graph=graph, retain_graph=True,
                                        allow_unused=True)[0] for i in range(self.n)]
        rows = [torch.zeros_like(p) if r is None else r for r in rows]
        if not graph:
            f = f.detach()
        w = torch.stack(rows, dim=1)[:, :, self.uncertain_index]
        return f, w

    def weighted_design(self, x: Tensor, u: Tensor, grad_v: Tensor) -> tuple[Tensor, Tensor]:
        """``(grad_v . f (B,), W^T grad_v (B, k))`` for a covector ``grad_v (B, n)``.

        One vector-Jacobian product instead of the full ``W``: this is the hot path of training.
        Differentiable (second order) in ``x``, ``u`` and ``grad_v``.
        """
        if self.perturbation is not None:
            f, w = self.true_dynamics(x, u), self.perturbation(x, u)
            return (grad_v * f).sum(-1), (grad_v.unsqueeze(-1) * w).sum(-2)
        if _enclosed(x):
            return self._weighted_design_forward(x, u, grad_v)
        graph = torch.is_grad_enabled()
        p = self.params(None, x).requires_grad_(True)
        with torch.enable_grad():
            s = (grad_v * self.dynamics(x, u, p)).sum(-1)
            (gp,) = torch.autograd.grad(s.sum(), p, create_graph=graph)
        if not graph:
            s = s.detach()
        return s, gp[:, self.uncertain_index]

    def _weighted_design_forward(self, x, u, grad_v):
        """:meth:`weighted_design` on enclosures: forward-mode derivatives in the uncertain parameters."""
        from drlyap.enclosures import Dual, Interval, is_enclosure, lift

        level = max(x.level, u.level if is_enclosure(u) else 0, grad_v.level)
        batch = x.shape[0]
        p = torch.tensor(self.nominal_params, dtype=torch.float64, device=x.device).expand(batch, -1)
        e = torch.zeros(batch, len(self.nominal_params), self.k, dtype=torch.float64, device=x.device)
        for j, i in enumerate(self.uncertain_index):
            e[:, i, j] = 1.0
        seeded = Dual(lift(Interval.const(p), level), lift(Interval.const(e), level))
        out = lift(self.dynamics(Dual(lift(x, level), None), Dual(lift(u, level), None), seeded), level + 1)
        if tuple(out.shape) != (batch, self.n):
            raise ValueError(f"{self.name}: dynamics returned shape {tuple(out.shape)} on enclosures, "
                             f"expected {(batch, self.n)}")
        w = out.d if out.d is not None else out.v.zeros_ext(self.k)  # None: F does not depend on p
        gv = lift(grad_v, level)
        return (gv * out.v).sum(-1), (gv.unsqueeze(-1) * w).sum(-2)

    def sample_xi(self, count: int, generator: torch.Generator) -> Tensor:
        """``count`` training samples ``(count, k)`` from the system's declared distribution."""
        if self.xi_sampler is None:
            raise ValueError(f"{self.name} declares no xi distribution; pass xi samples explicitly")
        draw = torch.as_tensor(self.xi_sampler(count, generator)).to(torch.float64)
        if draw.numel() != count * self.k or not torch.isfinite(draw).all():
            raise ValueError(f"{self.name}: xi_sampler({count}, generator) must return {count} finite rows of "
                             f"{self.k} values, got shape {tuple(draw.shape)}")
        return draw.reshape(count, self.k)

    def figure_starts(self, seed: int = 0, count: int = 2) -> list[tuple[float, ...]]:
        """Start states of the paper-like figures (user coordinates): ``reference_states``, else ``count`` states
        drawn uniformly from the test box with ``seed`` (its centre would often be x* itself, a flat line)."""
        if self.reference_states:
            return list(self.reference_states)
        lo, hi = (torch.tensor(side, dtype=torch.float64) for side in self.test_box)
        draw = torch.rand(count, self.n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        return [tuple(state) for state in (lo + (hi - lo) * draw).tolist()]

    def describe(self) -> dict:
        """A JSON-friendly summary (used by ``drlyap systems`` and saved in run directories)."""
        return {
            "name": self.name, "n": self.n, "m": self.m, "k": self.k,
            "states": list(self.state_names), "inputs": list(self.input_names),
            "parameters": dict(zip(self.param_names, self.nominal_params)),
            "uncertain": list(self.uncertain), "state_box": [list(b) for b in self.state_box],
            "input_box": [list(b) for b in self.input_box], "equilibrium": list(self.equilibrium),
            "equilibrium_input": list(self.equilibrium_input),
            "angle_dims": list(self.angle_dims), "test_box": [list(b) for b in self.test_box],
            "test_xi": list(self.test_xi) if self.test_xi is not None else None,
            "description": self.description,
            "state_units": list(self.state_units), "input_units": list(self.input_units), "time_unit": self.time_unit,
        }


def _enclosed(x) -> bool:
    """Whether ``x`` is one of :mod:`drlyap.enclosures`' enclosures (a tensor never is; the module loads only for
    what may be one)."""
    if isinstance(x, Tensor):
        return False
    from drlyap.enclosures import is_enclosure

    return is_enclosure(x)
