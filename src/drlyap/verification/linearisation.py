"""The closed-loop linearisation at x* and its quadratic Lyapunov function, for the local proof of
:mod:`drlyap.verification.roa` when the neural V's own second-order proof fails.

:func:`closed_loop_jacobians` computes ``A_j = dF_j/dz (0)`` of every sample's closed loop
``F_j(z) = f(x* + z, pi(z), xi_j)`` by running the system's and the controller's own code on dual numbers
(the same code path the verifier bounds; the result is the midpoint of a float64 interval enclosure).
:func:`lyapunov_matrix` solves ``A_s^T P_s + P_s A_s = -I`` in the coordinates scaled by the box's half-widths
``s`` (``z = S z_s``) and returns ``P = S^-1 P_s S^-1``, so ``W(z) = z^T P z`` has the Hessian of ``Wdot`` at
x* equal to ``-2 S^-2`` for that ``A``: negative definite and conditioned like the box, whatever V looks like.
:func:`common_lyapunov_matrix` picks one ``P`` for all samples' ``A_j`` (their mean's, improved numerically
where it fails for some ``A_j``).

For the mean-value proof of ``W`` on a cube (:func:`jacobian_negative`, used by
:func:`drlyap.verification.roa.quadratic_roa`): :func:`jacobian_enclosures` encloses every sample's Jacobian over
the cube (sound, affine forms), :func:`scaled_jacobians` puts the interval matrices in box-scaled coordinates
(rounded outward), :func:`robust_decrease_matrix` is the matrix whose negative definiteness is checked, and
:func:`robust_lyapunov_matrix` fits ``P`` and the bound's weights to it.

The fits prove nothing: ``A``, ``P`` and the weights only *choose* the certificate ``W``; what is claimed about
``W`` is proved afterwards by the verifier's enclosures, rounding pads and branch and bound
(:func:`drlyap.verification.roa.quadratic_roa`, :func:`drlyap.verification.roa.linearisation_local`).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import PlainDecrease
from drlyap.enclosures import F64, REL1, Affine, Dual, Interval, round_down, round_up
from drlyap.kinds import Model


def closed_loop_jacobians(loop: ClosedLoop, plain: PlainDecrease) -> list[Tensor]:
    """``A_j (n, n)`` for every sample ``xi_j`` of ``plain`` on its model (``true``: ``F(x, u, p0 + xi)``;
    ``design``: ``f + W xi``), at the local origin ``z = 0`` (the midpoints of :func:`jacobian_enclosures`)."""
    return [a.mid for a in jacobian_enclosures(loop, plain)]


def jacobian_enclosures(loop: ClosedLoop, plain: PlainDecrease, half: Tensor | None = None) -> list[Interval]:
    """For every sample of ``plain``, an interval matrix ``(n, n)`` containing ``dF_j/dz`` at every state of the
    cube ``|z_i| <= half_i`` (``half`` None: at ``z = 0``). The system's and the controller's own code runs on
    dual numbers over affine forms (:class:`~drlyap.enclosures.Affine`, whose vertex bound is within ~15% of the
    sampled range on the quadrotor's cubes), so for the controller's clamp it is the Clarke generalised Jacobian
    that is enclosed (the mean-value inclusion ``F(z) - F(0) in hull(J(cube)) z`` holds for it)."""
    system, controller = loop.system, loop.controller
    n = system.n
    eye = torch.eye(n, dtype=F64)

    def point(batch: int, tangent):  # the cube (or x*) as a dual number over affine forms, or intervals at x*
        if half is None:
            zero = torch.zeros(batch, n, dtype=F64)
            return Dual(Interval(zero, zero), Interval(tangent, tangent))
        lo, hi = (-half.to(F64))[None].expand(batch, n), half.to(F64)[None].expand(batch, n)
        return Dual(Affine.box(lo, hi), Affine.const(tangent))

    def finish(d) -> Interval:
        return d.tight_interval() if isinstance(d, Affine) else d

    out = []
    if plain.model == Model.TRUE:
        z = point(1, eye[None])
        x, u = system.to_user(z), controller(z)
        for xi in plain.xi:
            d = finish(system.true_dynamics(x, u, xi).d)
            out.append(Interval(d.lo[0], d.hi[0]))
        return out
    # design model: row i of F is e_i . (f + W xi), evaluated on n copies of the cube with unit covectors e_i
    z = point(n, eye[None].expand(n, n, n).clone())
    x, u = system.to_user(z), controller(z)
    gf, gw = system.weighted_design(x, u, Interval(eye, eye) if half is None else Affine.const(eye))
    for xi in plain.xi:
        out.append(finish((gf + (gw * Interval.const(xi)).sum(-1)).d))
    return out


def is_hurwitz(a: Tensor) -> tuple[bool, list[complex]]:
    """Whether every eigenvalue of ``a`` has a negative real part (numerically), and the eigenvalues."""
    ev = np.linalg.eigvals(a.numpy())
    return bool(np.all(ev.real < 0)), [complex(e) for e in ev]


def lyapunov_matrix(a: Tensor, half_widths: Tensor) -> Tensor:
    """``P`` with ``A^T P + P A = -S^-2`` (``S = diag(half_widths)``): the solution of the Lyapunov equation
    with ``Q = I`` in box-scaled coordinates, mapped back to local ones; symmetric, positive definite when
    ``A`` is Hurwitz."""
    s = half_widths.to(F64)
    a_s = (a * s[None, :] / s[:, None]).numpy()  # S^-1 A S
    p_s = scipy.linalg.solve_continuous_lyapunov(a_s.T, -np.eye(a.shape[0]))
    p = torch.as_tensor(p_s, dtype=F64) / s[:, None] / s[None, :]
    return (p + p.T) / 2


def decrease_rates(jacobians: Tensor | list[Tensor], p: Tensor, half_widths: Tensor) -> Tensor:
    """``(J,)``: for each ``A_j``, the largest eigenvalue of ``A_j^T P + P A_j`` over the smallest of ``P``, both
    in box-scaled coordinates: negative exactly when ``z^T P z`` decreases along ``A_j``'s linear flow."""
    s = torch.diag(half_widths.to(F64))
    a = torch.stack(list(jacobians)) if isinstance(jacobians, list) else jacobians
    low = torch.linalg.eigvalsh(s @ p @ s).min()
    return torch.linalg.eigvalsh(s @ (a.transpose(-1, -2) @ p + p @ a) @ s).amax(-1) / low


def common_lyapunov_matrix(jacobians: list[Tensor], half_widths: Tensor, steps: int = 2000) -> Tensor:
    """A ``P`` with ``A_j^T P + P A_j`` negative definite for every sample's ``A_j`` where one is found: the
    :func:`lyapunov_matrix` of their mean if it already is one (the usual case when the samples differ
    little), else that ``P`` improved by Adam on a Cholesky factor in box-scaled coordinates, minimising a
    soft maximum of :func:`decrease_rates` (the quadrotor's samples move its fast attitude mode from -106 to
    -129, and the mean's ``P`` fails for three of five). Returns the best ``P`` seen."""
    s = half_widths.to(F64)
    stack = torch.stack(jacobians).to(F64)
    p = lyapunov_matrix(stack.mean(0), s)
    if not bool(torch.isfinite(p).all()):
        return p
    best_rate = float(decrease_rates(stack, p, s).max())
    if best_rate < 0:
        return p
    a_s = stack * s[None, None, :] / s[None, :, None]  # S^-1 A_j S
    p_s = p * s[:, None] * s[None, :]
    factor, info = torch.linalg.cholesky_ex(p_s / torch.trace(p_s))
    if int(info) != 0:  # the mean's A is not Hurwitz: no starting point
        return p
    best, unit = p, torch.ones_like(s)
    with torch.enable_grad():
        factor = factor.clone().requires_grad_(True)
        opt = torch.optim.Adam([factor], lr=1e-3)
        for _ in range(steps):
            q = factor @ factor.T
            q = q / torch.trace(q)
            rates = decrease_rates(a_s, q, unit)  # already in box-scaled coordinates
            worst = float(rates.detach().max())
            if worst < best_rate:
                best_rate, best = worst, (q.detach() / s[:, None] / s[None, :])
            loss = torch.logsumexp(20 * rates / rates.detach().abs().max(), 0)
            opt.zero_grad()
            loss.backward()
            opt.step()
    return (best + best.T) / 2


def scaled_jacobians(enclosures: list[Interval], half_widths: Tensor) -> tuple[Tensor, Tensor]:
    """Centres and radii ``(J, n, n)`` of the interval matrices ``S^-1 [A_j] S`` (``S = diag(half_widths)``): every
    ``S^-1 A S`` with ``A`` in an enclosure lies within the radius (rounded up) of its centre, entrywise."""
    s = half_widths.to(F64)
    ratio = s[None, :] / s[:, None]
    lo = torch.stack([round_down(e.lo * ratio, REL1) for e in enclosures])
    hi = torch.stack([round_up(e.hi * ratio, REL1) for e in enclosures])
    centre = (lo + hi) / 2
    return centre, round_up(torch.maximum(hi - centre, centre - lo), REL1)


def robust_decrease_matrix(p: Tensor, centre: Tensor, radius: Tensor, log_t: Tensor) -> Tensor:
    """``M_j (J, n, n)`` with ``P A + A^T P <= M_j`` (as quadratic forms) for every ``A`` with
    ``|A - centre_j| <= radius_j`` entrywise::

        M = P C + C^T P + P D1 P + D2,   D1 = diag(sum_j R_ij t_ij),   D2 = diag(sum_i R_ij / t_ij)

    for any ``t = exp(log_t) > 0``: with ``E = A - C``, ``2 (Pz)^T E z <= 2 sum_ij |(Pz)_i| R_ij |z_j|
    <= sum_ij R_ij (t_ij (Pz)_i^2 + z_j^2 / t_ij)``. Unlike ``|P| R``, this keeps ``P``'s cancellations: on the
    quadrotor's cubes it proves a cube 16x wider per side than ``lambda_max(|P| R + R^T |P|)``."""
    t = log_t.exp()
    d1 = torch.diag_embed((radius * t).sum(-1))
    d2 = torch.diag_embed((radius / t).sum(-2))
    return p @ centre + centre.transpose(-1, -2) @ p + p @ d1 @ p + d2


def inscribed_log_volume(p: Tensor) -> Tensor:
    """``log`` of the volume (up to a constant) of the largest ellipsoid ``{z^T P z <= c}`` inside the unit cube
    ``|z_i| <= 1``: ``c = 1 / max_i (P^-1)_ii``, volume ``~ c^(n/2) / sqrt(det P)``. Invariant under scaling P."""
    n = p.shape[-1]
    return -n / 2 * torch.log(torch.linalg.inv(p).diagonal().max()) - 0.5 * torch.logdet(p)


def robust_lyapunov_matrix(centre: Tensor, radius: Tensor, p_start: Tensor, log_t: Tensor | None = None,
                           steps: int = 1500, fit_p: bool = True, volume: bool = False,
                           stop_below: float | None = None) -> tuple[Tensor, Tensor, float]:
    """``(P, log_t, rate)``: a ``P`` (scaled coordinates, ``lambda_min(P) = 1``; kept at ``p_start`` without
    ``fit_p``) and ``log_t (J, n, n)`` minimising the largest eigenvalue ``rate`` of
    :func:`robust_decrease_matrix` over the samples (Adam on a Cholesky factor and ``log_t``; the best seen).
    Negative ``rate``: ``z^T P z`` decreases along every linear field in the interval matrices. With ``volume``
    (from a ``p_start`` that already has a negative rate): among the ``P`` with ``rate`` below a twentieth of
    the start's, the one whose ellipsoid inscribed in the cube is largest (:func:`inscribed_log_volume`); the
    rate-only optimum is often a needle (on the quadrotor, volumes 1e-16 to 1e-11 of the box between fits).
    ``stop_below``: stop (rate fits only) once the rate is below it. This only *chooses* P and t: the verifier
    proves the claim with its own rounding pads."""
    eigenvalues = torch.linalg.eigvalsh(p_start)
    factor = torch.linalg.cholesky(p_start / eigenvalues.min())
    if log_t is None:  # t = 1 / lambda_max(P) balances the two terms of the bound for the stiffest direction
        log_t = torch.full_like(radius, -math.log(float(eigenvalues.max() / eigenvalues.min())))
    best = (p_start, log_t, math.inf)
    best_volume, target = -math.inf, None
    with torch.enable_grad():
        factor = factor.clone().requires_grad_(fit_p)
        log_t = log_t.clone().requires_grad_(True)
        opt = torch.optim.Adam([factor, log_t] if fit_p else [log_t], lr=3e-3 if volume else 1e-2 if fit_p else 5e-2)
        for _ in range(steps):
            p = factor @ factor.T
            p = p / torch.linalg.eigvalsh(p).min()
            rates = torch.linalg.eigvalsh(robust_decrease_matrix(p, centre, radius, log_t)).amax(-1)
            worst = float(rates.detach().max())
            if not math.isfinite(worst):
                break
            if volume:
                if target is None:
                    if not worst < 0:  # no margin to trade for volume
                        break
                    target = worst / 20
                log_volume = inscribed_log_volume(p)
                if worst < target and float(log_volume.detach()) > best_volume:
                    best_volume, best = float(log_volume.detach()), (p.detach().clone(), log_t.detach().clone(), worst)
                loss = 100 * torch.relu(rates - target).sum() / abs(target) - log_volume
            else:
                if worst < best[2]:
                    best = (p.detach().clone(), log_t.detach().clone(), worst)
                if stop_below is not None and worst < stop_below:
                    break
                loss = torch.logsumexp(20 * rates / rates.detach().abs().max(), 0)
            opt.zero_grad()
            loss.backward()
            opt.step()
    p, log_t, rate = best
    return (p + p.T) / 2, log_t, rate


def jacobian_negative(loop: ClosedLoop, plain: PlainDecrease, p: Tensor, half: Tensor, half_widths: Tensor,
                      log_t: Tensor | None = None,
                      scaled: tuple[Tensor, Tensor] | None = None) -> tuple[bool, float, str]:
    """Is ``Wdot = 2 z^T P F_j(z) < 0`` for every sample's model on the cube ``|z_i| <= half_i`` minus x*
    (``W = z^T P z``)?

    The mean-value form: ``F_j(0) = 0``, so ``F_j(z) = A z`` for some ``A`` in the hull of the enclosure of
    ``dF_j/dz`` over the cube (:func:`jacobian_enclosures`; the cube holds the
    segment from x* to z), and ``Wdot = z^T (P A + A^T P) z``. In the coordinates scaled by ``half_widths`` this
    is at most ``z_s^T M z_s`` with ``M`` of
    :func:`robust_decrease_matrix` (its ``t`` fitted here, any ``t`` is
    sound); ``M``'s largest eigenvalue plus a rounding pad of 1e-9 of the terms' norms below 0 proves it.
    Only first derivatives are enclosed (V's own Hessian test, :mod:`drlyap.verification.roa.local`, needs second ones).

    ``scaled``: that cube's :func:`scaled_jacobians` when the caller has them.

    Returns (proved, the bound ``lambda`` with ``Wdot <= lambda ||z||^2 / 2`` on the cube, reason)."""
    ok, bound, reason, _ = _jacobian_proof(loop, plain, p, half, half_widths, log_t, scaled)
    return ok, bound, reason


def decrease_weights(loop: ClosedLoop, plain: PlainDecrease, p: Tensor, half: Tensor,
                     half_widths: Tensor) -> Tensor | None:
    """The weights ``tau (J, n, n) > 0`` with which :func:`jacobian_negative` proves ``W = z^T P z`` decreasing on the
    cube ``|z_i| <= half_i``, in local (unscaled) coordinates: ``P A + A^T P <= P C + C^T P + P D1 P + D2`` with
    ``D1 = diag(sum_j R_ij tau_ij)``, ``D2 = diag(sum_i R_ij / tau_ij)`` for ``|A - C| <= R`` (what a certificate of
    the closed loop's ellipsoid states, for the checker to redo the test); None where it is not proved."""
    ok, _, _, found = _jacobian_proof(loop, plain, p, half, half_widths, None, None)
    if not ok:
        return None
    log_t, unit = found
    s = half_widths.to(F64)
    return (log_t + s.log()[:, None] + s.log()[None, :] - math.log(unit)).exp()


def _jacobian_proof(loop: ClosedLoop, plain: PlainDecrease, p: Tensor, half: Tensor, half_widths: Tensor,
                    log_t: Tensor | None,
                    scaled: tuple[Tensor, Tensor] | None) -> tuple[bool, float, str, tuple[Tensor, float] | None]:
    """:func:`jacobian_negative`, also returning the weights ``log_t`` (scaled coordinates) and the scale ``unit`` of
    ``P`` the proof used."""
    s = half_widths.to(F64)
    centre, radius = scaled or scaled_jacobians(jacobian_enclosures(loop, plain, half), s)
    if not bool(torch.isfinite(centre).all() and torch.isfinite(radius).all()):
        return False, math.nan, "non-finite Jacobian enclosure", None
    p_s = p.to(F64) * s[:, None] * s[None, :]
    unit = float(torch.linalg.eigvalsh(p_s).min())  # P / unit has lambda_min 1, as robust_lyapunov_matrix's
    if not unit > 0:
        return False, math.nan, "P is not positive definite", None
    p_n = p_s / unit

    def proved_rate(log_t: Tensor) -> float:
        m = robust_decrease_matrix(p_n, centre, radius, log_t)
        t = log_t.exp()
        norms = (2 * torch.linalg.matrix_norm(p_n) * torch.linalg.matrix_norm(centre)
                 + torch.linalg.matrix_norm(p_n) ** 2 * (radius * t).sum(-1).amax(-1)
                 + (radius / t).sum(-2).amax(-1) + torch.linalg.matrix_norm(m))
        top = torch.linalg.eigvalsh(m).amax(-1) + 1e-9 * norms + 1e-300
        return float(top.max())

    worst = proved_rate(log_t) if log_t is not None else math.nan
    for stop in (0.0, None):  # fit t: first until the rate is negative, then (if the pads undo it) all the way
        if worst < 0:
            break
        _, log_t, _ = robust_lyapunov_matrix(centre, radius, p_n, log_t, steps=300, fit_p=False, stop_below=stop)
        worst = proved_rate(log_t)
    if not worst < 0:  # NaN included
        return False, math.nan, "P A + A^T P not provably negative definite over the Jacobian enclosure", None
    return True, 2 * unit * worst / float(s.max()) ** 2, "", (log_t, unit)
