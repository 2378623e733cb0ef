"""Regions of attraction that reach x*, checked independently by simulation on the true model; and the case
where only practical stability is proved (the equilibrium moves with xi)."""

import json
import math
from dataclasses import replace

import torch

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRPointwise, TrueDecrease
from drlyap.enclosures import Affine
from drlyap.lqr import lqr_design
from drlyap.networks import LinearController, QuadraticLyapunov
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.render import roa_cell, roa_line
from drlyap.simulation import simulate
from drlyap.systems import UncertainSystem, get_system
from drlyap.verification import RegionOfAttraction, certified_roa, local_decrease
from drlyap.verification.linearisation import (
    closed_loop_jacobians,
    common_lyapunov_matrix,
    decrease_rates,
    lyapunov_matrix,
    robust_decrease_matrix,
)
from drlyap.verification.roa import band_roa, linearisation_local, quadratic_roa, share_of_box
from drlyap.verification.roa.levels import outside_lower, vertex_max
from drlyap.verification.roa.sublevel import TRAINED_LEVEL
from drlyap.verification.roa_steps import BandRegion, LinearisationProof, LocalProof, QuadraticRegion
from handmade import bump_pair, linear_pair, small_pendulum

F64 = torch.float64
XI = torch.tensor([[0.02, 0.01], [-0.03, 0.0], [0.05, -0.02]], dtype=F64)


def _inside(system, lyap, level, count, seed):
    lo, hi = system.local_box()
    g = torch.Generator().manual_seed(seed)
    z = lo + (hi - lo) * torch.rand(20 * count, system.n, generator=g, dtype=F64)
    with torch.no_grad():
        v = lyap.double()(z)
    return z[v <= level][:count]


def _assert_stays_and_converges(system, lyap, ctrl, z0, xi, level, horizon):
    """Trajectories of the true model at ``xi`` from local states ``z0`` keep ``V <= level`` and reach x*."""
    traj = simulate(system, lambda x: ctrl(system.to_local(x)), system.to_user(z0), torch.tensor(xi, dtype=F64),
                    dt=0.005, horizon=horizon)
    with torch.no_grad():
        v = lyap(system.to_local(traj.x.reshape(-1, 2))).reshape(traj.x.shape[:2])
    assert float(v.max()) <= level * (1 + 1e-9)
    assert float(system.to_local(traj.x[-1]).norm(dim=-1).max()) < 1e-3


def test_every_certified_set_converges_to_x_star_on_the_true_model():
    """Sample states in each certified {V <= c} (true model at several shifts), simulate the true closed loop:
    every trajectory converges to x* and V never rises above c."""
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    l64, c64 = lyap.double(), ctrl.double()
    for xi in ([0.1, 0.05], [0.0, 0.0], [-0.05, 0.1]):
        condition = TrueDecrease(torch.tensor([xi], dtype=F64), 0.05)
        roa = certified_roa(ClosedLoop(system, lyap, ctrl), condition, Region.of(system, 0.2), Budget(seconds=10),
                            samples_per_axis=100)
        assert roa.kind == "region of attraction" and roa.certified and roa.local.proved, roa
        level = roa.level
        z0 = _inside(system, l64, level, 200, seed=len(xi))
        assert z0.shape[0] >= 100
        _assert_stays_and_converges(system, l64, c64, z0, xi, level, horizon=12.0)


def test_design_model_roa_for_the_dr_condition_proves_the_ball_too():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    local = local_decrease(ClosedLoop(system, lyap, ctrl), DRPointwise(1e-3, 0.1, XI, 0.05),
                           Region.of(system, 0.2))
    assert local.proved and local.hessian_bound < 0
    # with eps N > 1 the CVaR is not a max over samples: no per-sample trajectory claim
    local = local_decrease(ClosedLoop(system, lyap, ctrl), DRPointwise(1e-3, 0.5, XI, 0.05),
                           Region.of(system, 0.2))
    assert not local.proved and "per-sample" in local.reason


def _offset_integrator() -> UncertainSystem:
    def dyn(x, u, p):
        c, d = p.unbind(-1)
        return torch.stack([x[:, 1], -c * x[:, 1] + u[:, 0] + d], -1)

    return UncertainSystem(
        name="offset-integrator", state_names=("q", "v"), input_names=("f",), param_names=("damping", "offset"),
        nominal_params=(0.5, 0.0), uncertain=("offset",), dynamics=dyn, state_box=((-1, -1), (1, 1)),
        input_box=((-5,), (5,)), equilibrium=(0.0, 0.0))


def _lqr_like_pair(system):
    k = torch.tensor([[2.0, 2.0]], dtype=F64)
    a_cl = torch.tensor([[0.0, 1.0], [0.0, -0.5]], dtype=F64) - torch.tensor([[0.0], [1.0]], dtype=F64) @ k
    eye = torch.eye(2, dtype=F64)
    lhs = torch.kron(eye, a_cl.T.contiguous()) + torch.kron(a_cl.T.contiguous(), eye)
    p = torch.linalg.solve(lhs, -eye.reshape(-1)).reshape(2, 2)
    return QuadraticLyapunov((p + p.T) / 2), LinearController(k, system.input_box, system.equilibrium_input)


def test_a_moved_equilibrium_is_practical_stability_not_a_region_of_attraction():
    """A constant disturbance (uncertain offset) moves the closed loop's equilibrium away from x*: decrease holds
    outside the ball (the old annulus-only certificate) but not inside, so the claim is practical stability."""
    system = _offset_integrator()
    lyap, ctrl = _lqr_like_pair(system)
    condition = TrueDecrease(torch.tensor([[0.05]], dtype=F64), 0.01)
    roa = certified_roa(ClosedLoop(system, lyap, ctrl), condition, Region.of(system, 0.3), Budget(seconds=10),
                        samples_per_axis=100)
    assert roa.level > roa.ball_max_upper > 0  # the annulus-only certificate exists...
    assert roa.kind == "practical stability" and not roa.certified  # ...and is not called an ROA
    assert "not an equilibrium" in roa.local.reason
    # and indeed the true closed loop settles away from x*, inside {V <= practical_level}
    z0 = _inside(system, lyap, roa.level, 50, seed=3)
    traj = simulate(system, lambda x: ctrl(system.to_local(x)), system.to_user(z0), torch.tensor([0.05], dtype=F64),
                    dt=0.01, horizon=20.0)
    end = traj.x[-1]
    assert float(end.norm(dim=-1).min()) > 1e-3
    assert float(lyap(end).max()) <= roa.practical_level
    # at xi = 0 the same pair has a region of attraction
    nominal = certified_roa(ClosedLoop(system, lyap, ctrl), TrueDecrease(torch.zeros(1, 1, dtype=F64), 0.01),
                            Region.of(system, 0.3), Budget(seconds=10), samples_per_axis=100)
    assert nominal.kind == "region of attraction" and math.isfinite(nominal.level)


def test_lyapunov_matrix_solves_the_scaled_lyapunov_equation():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    condition = TrueDecrease(torch.tensor([[0.1, 0.05]], dtype=F64))
    (a,) = closed_loop_jacobians(ClosedLoop(system, None, ctrl), condition)
    x0 = system.to_user(torch.zeros(1, 2, dtype=F64))

    def field(z):
        return system.true_dynamics(system.to_user(z[None]), ctrl.double()(z[None]), condition.xi[0])[0]

    assert torch.allclose(a, torch.autograd.functional.jacobian(field, torch.zeros(2, dtype=F64)), atol=1e-9)
    assert float(x0.abs().max()) == 0.0
    s = torch.tensor([0.6, 1.2], dtype=F64)
    p = lyapunov_matrix(a, s)
    assert torch.allclose(a.T @ p + p @ a, -torch.diag(1 / s ** 2), atol=1e-9)
    assert float(torch.linalg.eigvalsh(p).min()) > 0


def test_one_quadratic_decreases_along_every_samples_linearisation():
    """Jacobians whose mean's Lyapunov matrix fails for both (a slow and a fast mode coupled, the fast one
    moved 100x by the samples): the common P decreases along each; where the mean's works, it is kept."""
    half = torch.tensor([0.5, 2.0], dtype=F64)
    jacobians = [torch.tensor([[-1.0, 10.0], [0.0, -t]], dtype=F64) for t in (1.0, 100.0)]
    mean = lyapunov_matrix(torch.stack(jacobians).mean(0), half)
    assert bool((decrease_rates(jacobians, mean, half) > 0).all())
    p = common_lyapunov_matrix(jacobians, half)
    assert float(torch.linalg.eigvalsh(p).min()) > 0
    for a in jacobians:
        assert float(torch.linalg.eigvalsh(a.T @ p + p @ a).max()) < 0
    close = [torch.tensor([[-1.0, 1.0], [0.0, -t]], dtype=F64) for t in (2.0, 2.2)]
    assert torch.equal(common_lyapunov_matrix(close, half), lyapunov_matrix(torch.stack(close).mean(0), half))


def test_the_linearisation_proves_the_ball_where_the_hessian_of_v_cannot():
    """V = (linear pair) + a narrow bump: V's quadratic part at x* is no Lyapunov function of the closed-loop
    linearisation (its own second-order proof fails, and V does increase near x*), but the linearisation's
    z'Pz proves the ball: {V <= c} is a region of attraction. Checked by simulating the true model from
    states sampled in it, including states where V increases."""
    system = small_pendulum()
    lyap, ctrl = bump_pair(system, kappa=100.0, beta=1e-3)
    xi = [0.1, 0.05]
    condition = TrueDecrease(torch.tensor([xi], dtype=F64), 0.05)
    region = Region.of(system, 0.2)
    assert not local_decrease(ClosedLoop(system, lyap, ctrl), condition, region).proved
    roa = certified_roa(ClosedLoop(system, lyap, ctrl), condition, region, Budget(seconds=10), samples_per_axis=100)
    local = roa.local
    assert roa.kind == "region of attraction" and roa.certified, roa
    assert local.method == "linearisation" and local.proved and not local.second_order.proved
    assert 0 < local.inner_level < roa.level and local.q_level > 0 and roa.share_of_box > 0.3
    _assert_reads_back(roa, LinearisationProof)
    level = roa.level
    l64, c64 = lyap.double(), ctrl.double()
    z0 = _inside(system, l64, level, 300, seed=11)
    rising = ClosedLoop(system, lyap, ctrl).exact(condition, z0) > 0  # V increases there (inside the ball)
    assert z0.shape[0] >= 200 and int(rising.sum()) >= 1
    _assert_stays_and_converges(system, l64, c64, z0, xi, level, horizon=15.0)


def test_no_region_of_attraction_when_the_linearisation_is_not_hurwitz():
    system = small_pendulum()
    lyap, ctrl = bump_pair(system, kappa=100.0, beta=1e-3)
    flipped = linear_pair(system, sign=-1.0)[1]  # positive feedback: the closed loop is unstable at x*
    condition = TrueDecrease(torch.tensor([[0.1, 0.05]], dtype=F64), 0.05)
    region = Region.of(system, 0.2)
    local = linearisation_local(ClosedLoop(system, lyap, flipped), condition, region, 1.0, Budget(seconds=5))
    assert not local.proved and "not Hurwitz" in local.reason
    roa = certified_roa(ClosedLoop(system, lyap, flipped), condition, region, Budget(seconds=5), samples_per_axis=50)
    assert roa.kind != "region of attraction" and not roa.certified


def test_a_capped_search_certifies_the_level_asked_for_and_no_more():
    """``max_level`` below the largest certifiable level: the search stops at the cap (one rounding step below),
    says so, and the set is still a region of attraction whose trajectories converge."""
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    condition = TrueDecrease(torch.tensor([[0.0, 0.0]], dtype=F64), 0.05)
    full = certified_roa(ClosedLoop(system, lyap, ctrl), condition, Region.of(system, 0.2), Budget(seconds=10),
                         samples_per_axis=50)
    cap = full.level / 3
    capped = certified_roa(ClosedLoop(system, lyap, ctrl), condition, Region.of(system, 0.2), Budget(seconds=10),
                           samples_per_axis=50, max_level=cap)
    assert capped.certified and capped.limited_by == TRAINED_LEVEL, capped
    assert cap * (1 - 1e-12) <= capped.level <= cap
    assert capped.share_of_box < full.share_of_box
    z0 = _inside(system, lyap.double(), capped.level, 50, seed=3)
    _assert_stays_and_converges(system, lyap.double(), ctrl.double(), z0, [0.0, 0.0], capped.level, horizon=12.0)


def test_robust_decrease_matrix_bounds_every_matrix_of_the_interval():
    """``P A + A^T P <= M`` (as quadratic forms) for random ``A`` in ``[C - R, C + R]``, vertices included, and
    any ``t``."""
    g = torch.Generator().manual_seed(0)
    n = 5
    b = torch.randn(n, n, generator=g, dtype=F64)
    p = b @ b.T + 0.1 * torch.eye(n, dtype=F64)
    centre = torch.randn(2, n, n, generator=g, dtype=F64)
    radius = torch.rand(2, n, n, generator=g, dtype=F64)
    log_t = torch.randn(2, n, n, generator=g, dtype=F64)
    m = robust_decrease_matrix(p, centre, radius, log_t)
    signs = torch.rand(500, 2, n, n, generator=g, dtype=F64) * 2 - 1
    signs[:250] = signs[:250].sign()  # vertices of the interval matrix
    a = centre + radius * signs
    gap = m - (p @ a + a.transpose(-1, -2) @ p)
    assert float(torch.linalg.eigvalsh(gap).min()) >= -1e-9 * float(m.abs().max())


def test_quadratic_region_of_the_quadrotor_decreases_and_converges():
    """6 states: the closed loop of an LQR on the quadrotor (true model at the test shift and the nominal). The
    certified ellipsoid {z'Pz <= c}: z'Pz decreases at every sampled state of it, for both models, and
    trajectories from it converge to x* (simulated on the true model)."""
    system = get_system("quadrotor2d")
    design = lqr_design(system)
    ctrl = LinearController(design.K, system.input_box, system.equilibrium_input)
    shifts = [list(system.test_xi), [0.0, 0.0]]
    condition = TrueDecrease(torch.tensor(shifts, dtype=F64), 0.05)
    out = quadratic_roa(ClosedLoop(system, None, ctrl), condition, Region.of(system, 0.1),
                        Budget(seconds=15, enclosure="affine"))
    assert out.proved and out.q_level > 0 and out.cube_level <= out.q_level, out.reason
    p, level = torch.tensor(out.P, dtype=F64), out.q_level
    g = torch.Generator().manual_seed(1)
    u = torch.randn(4000, 6, generator=g, dtype=F64)
    u = u / u.norm(dim=-1, keepdim=True) * torch.rand(4000, 1, generator=g, dtype=F64) ** (1 / 6)
    z = math.sqrt(level) * torch.linalg.solve_triangular(torch.linalg.cholesky(p).T, u.T, upper=True).T
    assert float(QuadraticLyapunov(p)(z).max()) <= level * (1 + 1e-9)
    w = QuadraticLyapunov(p)
    for xi in shifts:
        assert float(ClosedLoop(system, w, ctrl).exact(TrueDecrease(torch.tensor([xi], dtype=F64), 0.0), z).max()) < 0
        traj = simulate(system, lambda x: ctrl(system.to_local(x)), system.to_user(z[:100]),
                        torch.tensor(xi, dtype=F64), dt=0.004, horizon=10.0)
        with torch.no_grad():
            values = w(system.to_local(traj.x.reshape(-1, 6))).reshape(traj.x.shape[:2])
        assert float(values.max()) <= level * (1 + 1e-9)
        assert float(system.to_local(traj.x[-1]).norm(dim=-1).max()) < 1e-3


def test_the_closed_loops_quadratic_region_is_reported_where_no_sublevel_set_of_v_is():
    """V = theta^2 + omega^2 / 100 does not decrease along the linear pair's closed loop near x* (its level
    search and local proofs fail), yet the controller's closed loop is stable: without the band proof the result
    certifies no set of V, reports the quadratic {z'Pz <= c} instead, and the CLI names it for what it is."""
    system = small_pendulum()
    _, ctrl = linear_pair(system)
    wrong = QuadraticLyapunov(torch.diag(torch.tensor([1.0, 0.01], dtype=F64)))
    condition = TrueDecrease(torch.tensor([[0.1, 0.05]], dtype=F64), 0.05)
    roa = certified_roa(ClosedLoop(system, wrong, ctrl), condition, Region.of(system, 0.2), Budget(seconds=10),
                        samples_per_axis=50, band_time=0)
    assert not roa.certified and roa.band is None
    quad = roa.quadratic
    assert quad.proved and quad.q_level > 0 and quad.share_of_box > 0, quad
    line = roa_line(roa, true_model=True)
    assert "region of attraction: NOT CERTIFIED" in line and "CERTIFIED region of attraction {z'Pz <=" in line
    w = QuadraticLyapunov(torch.tensor(quad.P, dtype=F64))
    z0 = _inside(system, w.double(), quad.q_level, 100, seed=5)
    assert z0.shape[0] >= 20
    _assert_stays_and_converges(system, w.double(), ctrl.double(), z0, [0.1, 0.05], quad.q_level, horizon=12.0)


def _outside_points(lyap, p, c_q, level, system, count, seed):
    """Uniform states of the box in {V <= level} with z'Pz > c_q (outside the ellipsoid)."""
    z = _inside(system, lyap, level, 50 * count, seed)
    return z[QuadraticLyapunov(p)(z) > c_q][:count]


def test_band_proof_extends_the_closed_loops_ellipsoid_to_a_sublevel_set_of_v():
    """The band proof: V decreases on {V <= c} outside the closed loop's certified ellipsoid L. Its level reaches
    beyond L (V's smallest value on L's boundary), V decreases at every sampled state of {V <= c} outside L, and
    trajectories of the true model from {V <= c} converge to x*."""
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    l64 = lyap.double()
    xi = [0.1, 0.05]
    condition = TrueDecrease(torch.tensor([xi], dtype=F64), 0.05)
    region = Region.of(system, 0.2)
    quad = quadratic_roa(ClosedLoop(system, None, ctrl), condition, region, Budget(seconds=5, enclosure="affine"))
    assert quad.proved
    band = band_roa(ClosedLoop(system, lyap, ctrl), condition, region, quad, top=1.0, budget=Budget(seconds=10))
    assert band.proved and band.level > band.v_on_ellipsoid[0] and band.beyond_ellipsoid, band
    p = torch.tensor(quad.P, dtype=F64)
    z = _outside_points(l64, p, quad.q_level, band.level, system, 300, seed=7)
    assert z.shape[0] >= 100
    assert float(ClosedLoop(system, l64, ctrl.double()).exact(TrueDecrease(torch.tensor([xi], dtype=F64), 0.0), z)
                 .max()) < 0
    c64 = ctrl.double()  # the proof claims convergence from the set (it and L together are invariant, not it alone)
    traj = simulate(system, lambda x: c64(system.to_local(x)), system.to_user(z[:100]), torch.tensor(xi, dtype=F64),
                    dt=0.005, horizon=12.0)
    assert float(system.to_local(traj.x[-1]).norm(dim=-1).max()) < 1e-3


def test_band_proof_never_certifies_where_v_rises_outside_the_ellipsoid():
    """V = theta^2 + omega^2 / 100 rises along the linear pair's closed loop near x*, outside every ellipsoid of
    it: whatever level the band proof returns, no sampled state of {V <= c} outside L has Vdot > 0."""
    system = small_pendulum()
    _, ctrl = linear_pair(system)
    wrong = QuadraticLyapunov(torch.diag(torch.tensor([1.0, 0.01], dtype=F64)))
    condition = TrueDecrease(torch.tensor([[0.1, 0.05]], dtype=F64), 0.05)
    region = Region.of(system, 0.2)
    quad = quadratic_roa(ClosedLoop(system, None, ctrl), condition, region, Budget(seconds=5, enclosure="affine"))
    band = band_roa(ClosedLoop(system, wrong, ctrl), condition, region, quad, top=0.3, budget=Budget(seconds=5))
    if band.proved:
        p = torch.tensor(quad.P, dtype=F64)
        z = _outside_points(wrong, p, quad.q_level, band.level, system, 2000, seed=8)
        if z.shape[0]:
            plain = TrueDecrease(torch.tensor([[0.1, 0.05]], dtype=F64), 0.0)
            values = ClosedLoop(system, wrong, ctrl.double()).exact(plain, z)
            assert float(values.max()) < 0
    # and V does rise just outside L somewhere below V = 0.3: the proof stopped short of 0.3
    assert band.level is None or band.level < 0.3


def test_lower_bound_of_v_outside_an_ellipsoid_is_sound_on_random_boxes():
    """outside_lower on the affine forms of V (a tanh pair) and W over boxes straddling W = c_q is at most the
    smallest sampled V on the box's part with W >= c_q; vertex_max bounds W on the box from above and matches
    its largest vertex."""
    system = small_pendulum()
    lyap, _ = linear_pair(system)
    l64 = lyap.double()
    p = torch.tensor([[2.0, 0.3], [0.3, 0.5]], dtype=F64)
    w = QuadraticLyapunov(p)
    c_q = 0.05
    g = torch.Generator().manual_seed(3)
    centre = 0.3 * (torch.rand(200, 2, generator=g, dtype=F64) - 0.5)
    half = 0.02 + 0.1 * torch.rand(200, 2, generator=g, dtype=F64)
    lo, hi = centre - half, centre + half
    form = torch.stack([w(Affine.box(lo, hi)), l64(Affine.box(lo, hi))], -1)
    at_v, at_w = l64(centre), w(centre)
    for level in (0.01, 0.1):
        bound = outside_lower(form[:, 1], form[:, 0], at_v, at_w, c_q, level)
        t = torch.rand(200, 4000, 2, generator=g, dtype=F64)
        z = lo[:, None] + (hi - lo)[:, None] * t
        with torch.no_grad():
            v = l64(z.reshape(-1, 2)).reshape(200, -1)
        wz = (z @ p * z).sum(-1)
        v_out = torch.where(wz >= c_q, v, torch.inf).amin(-1)
        assert bool((bound <= v_out).all())
        assert int(torch.isfinite(v_out).sum()) > 50 and int((bound > -torch.inf).sum()) > 50
    top = vertex_max(p, lo, hi)
    corners = torch.stack([lo, torch.stack([lo[:, 0], hi[:, 1]], -1), torch.stack([hi[:, 0], lo[:, 1]], -1), hi], 1)
    exact = (corners @ p * corners).sum(-1).amax(-1)
    assert bool((top >= exact).all()) and bool((top <= exact * (1 + 1e-12) + 1e-300).all())


def test_share_of_a_small_set_is_estimated_on_nested_boxes():
    """In 6 states a sublevel set far below 1e-5 of the box gets no uniform sample; the stratified estimate over
    nested boxes is within 10% of the ellipsoid's exact volume share."""
    system = get_system("quadrotor2d")
    region = Region.of(system, 0.1)
    p = torch.diag(torch.tensor([4.0, 9.0, 25.0, 1.0, 1.0, 2.0], dtype=F64))
    v = QuadraticLyapunov(p)
    for level in (1e-3, 1e-2):
        exact = (math.pi ** 3 / 6 * level ** 3 / math.sqrt(float(torch.linalg.det(p)))
                 / float(region.scale.prod()))
        share = share_of_box(v, region, level, 400)
        assert abs(share - exact) < 0.1 * exact, (share, exact)


def test_certified_roa_falls_back_to_the_band_proof_and_names_it():
    """Where the level search and the local proofs certify no sublevel set of V (V rises near x*), the band proof
    from the closed loop's ellipsoid may: the result is then a region of attraction by the band, the CLI says
    so, and trajectories of the true model from the set converge to x* (V need not decrease inside L)."""
    system = small_pendulum()
    _, ctrl = linear_pair(system)
    wrong = QuadraticLyapunov(torch.diag(torch.tensor([1.0, 0.01], dtype=F64)))
    xi = [0.1, 0.05]
    condition = TrueDecrease(torch.tensor([xi], dtype=F64), 0.05)
    roa = certified_roa(ClosedLoop(system, wrong, ctrl), condition, Region.of(system, 0.2), Budget(seconds=10),
                        samples_per_axis=50)
    assert roa.certified and roa.local.method == "band" and roa.quadratic.proved, roa
    assert roa.level == roa.band.level > 0
    _assert_reads_back(roa, BandRegion)
    line = roa_line(roa, true_model=True)
    assert "CERTIFIED {V <=" in line and "outside the closed loop's certified ellipsoid" in line
    z0 = _inside(system, wrong.double(), roa.level, 100, seed=9)
    assert z0.shape[0] >= 20
    c64 = ctrl.double()
    traj = simulate(system, lambda x: c64(system.to_local(x)), system.to_user(z0), torch.tensor(xi, dtype=F64),
                    dt=0.005, horizon=12.0)
    assert float(system.to_local(traj.x[-1]).norm(dim=-1).max()) < 1e-3


def _assert_reads_back(roa: RegionOfAttraction, local_kind: type) -> None:
    """The region's JSON reads back as the same typed steps (the proof near x* by its method)."""
    back = RegionOfAttraction.from_dict(json.loads(json.dumps(roa.to_dict())))
    assert isinstance(back.local, local_kind) and back.to_dict() == json.loads(json.dumps(roa.to_dict()))
    assert back.quadratic is None or isinstance(back.quadratic, QuadraticRegion)


def test_report_cell_says_whether_the_band_set_reaches_beyond_the_ellipsoid():
    band = BandRegion(v_on_ellipsoid=[0.0165, 0.27], beyond_ellipsoid=True)
    roa = RegionOfAttraction(level=0.0185, kind="region of attraction", share_of_box=4.1e-9, local=band)
    assert roa_cell(roa) == "4.1e-09 of box (V, band)"
    inside = replace(band, beyond_ellipsoid=False)
    assert roa_cell(RegionOfAttraction(level=0.0119, kind="region of attraction", share_of_box=4.1e-9,
                                       local=inside)) == "4.1e-09 of box (V, within z'Pz)"
    assert roa_cell(RegionOfAttraction(level=1.0, kind="region of attraction", share_of_box=0.35,
                                       local=LocalProof("second order", proved=True))) == "35.0%"


def test_a_region_recorded_with_fewer_fields_reads_back():
    """A region as an older metrics.json may hold it (steps without fields added since) reads back as typed steps."""
    stored = {"level": 0.2, "kind": "region of attraction", "certified": True,
              "local": {"method": "linearisation", "proved": True, "level": 0.2, "annulus": {"level": 0.2},
                        "quadratic": {"proved": True, "candidates": [{"P": [[1.0, 0.0], [0.0, 1.0]], "q_level": 0.1,
                                                                       "q_roa": {"level": 0.1}}]}},
              "quadratic": {"proved": True, "q_level": 0.1, "P": [[1.0, 0.0], [0.0, 1.0]]},
              "band": {"method": "band", "proved": False, "levels": [{"level": 1.0}]},
              "strict": {"strict": True, "by": "decay"}}
    roa = RegionOfAttraction.from_dict(stored)
    assert isinstance(roa.local, LinearisationProof) and roa.local.annulus.level == 0.2
    assert roa.local.quadratic.candidates[0].q_roa.level == 0.1 and roa.ellipsoid_certified
    assert roa.band.levels[0].level == 1.0 and roa.strict.by == "decay" and roa.method == "linearisation"
    assert RegionOfAttraction.from_dict({"error": "no search"}).local is None
