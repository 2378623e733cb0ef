"""The built-in higher-dimensional systems: cart-pole (4 states) and planar quadrotor (6 states)."""

import math

import pytest
import torch

from drlyap.enclosures import Interval
from drlyap.lqr import lqr_design
from drlyap.simulation import evaluate, initial_states
from drlyap.systems import get_system, resolve_system, system_names
from drlyap.training import TrainConfig, TrainSections

torch.set_num_threads(1)

NAMES = ["cartpole", "quadrotor2d"]
F64 = torch.float64


def _points(system, count, seed=0, scale=1.0):
    """Random states in the (scaled) state box and inputs in U, float64."""
    gen = torch.Generator().manual_seed(seed)
    slo, shi = (torch.tensor(b, dtype=F64) for b in system.state_box)
    ulo, uhi = (torch.tensor(b, dtype=F64) for b in system.input_box)
    x = (slo + (shi - slo) * torch.rand(count, system.n, generator=gen, dtype=F64)) * scale
    u = ulo + (uhi - ulo) * torch.rand(count, system.m, generator=gen, dtype=F64)
    return x, u


def _design(system, x, u):
    """``f, W`` of the design model, without the autograd graph."""
    with torch.no_grad():
        return system.design_model(x, u)


def _all_xi(system):
    """Nominal, every training sample of the declared distribution and the test shift: (N, k)."""
    samples = system.sample_xi(5, torch.Generator().manual_seed(0))
    return torch.cat([torch.zeros(1, system.k, dtype=F64), samples, torch.tensor([system.test_xi], dtype=F64)])


@pytest.mark.parametrize("name", NAMES)
def test_registered_with_shapes(name):
    system = get_system(name)
    assert name in system_names() and resolve_system(name).describe() == system.describe()
    n, m = {"cartpole": (4, 1), "quadrotor2d": (6, 2)}[name]
    assert (system.n, system.m, system.k) == (n, m, 2)
    assert len(system.state_units) == n and len(system.input_units) == m
    x, u = _points(system, 7)
    assert system.true_dynamics(x, u).shape == (7, n)
    assert system.true_dynamics(x, u, torch.tensor(system.test_xi, dtype=F64)).shape == (7, n)
    f, w = _design(system, x, u)
    assert f.shape == (7, n) and w.shape == (7, n, 2)
    assert system.sample_xi(5, torch.Generator().manual_seed(1)).shape == (5, 2)
    assert all(len(s) == n for s in system.figure_starts())
    lo, hi = system.test_box
    assert all(a <= v <= b for s in system.figure_starts() for a, v, b in zip(lo, s, hi))


@pytest.mark.parametrize("name", NAMES)
def test_equilibrium_for_nominal_every_sample_and_the_test_shift(name):
    system = get_system(name)
    xis = _all_xi(system)
    x = torch.tensor([system.equilibrium], dtype=F64).expand(xis.shape[0], -1)
    u = torch.tensor([system.equilibrium_input], dtype=F64).expand(xis.shape[0], -1)
    assert system.true_dynamics(x, u, xis).abs().max() < 1e-12
    f, w = _design(system, x[:1], u[:1])
    assert f.abs().max() < 1e-12 and w.abs().max() < 1e-12  # x* stays an equilibrium of f + W xi too


def test_quadrotor_hover_input_and_asymmetric_input_box():
    system = get_system("quadrotor2d")
    hover = 0.486 * 9.81 / 2
    assert system.equilibrium_input == pytest.approx((hover, hover), rel=1e-15)
    assert system.input_box == ((0.0, 0.0), (5.96, 5.96))
    lyapunov, controller = TrainSections.of(TrainConfig(system="quadrotor2d").resolved(system)).networks.build(system)
    zero = torch.zeros(1, 6, dtype=torch.float32)
    assert torch.allclose(controller(zero).double(), torch.tensor([[hover, hover]], dtype=F64), atol=1e-6)
    z = torch.randn(100, 6) * 5
    out = controller(z)
    ulps = 8 * torch.finfo(torch.float32).eps * 5.96  # float32 rounding of u* + (U - u*)
    assert bool((out >= -ulps).all() and (out <= 5.96 + ulps).all())
    assert float(lyapunov(zero).detach()) == 0.0


def test_cartpole_equals_tedrake_without_damping_and_lagrange_with_it():
    """b = 0: Tedrake's equations; b > 0: the solution of M(q) qddot = forces with tau = -b thd."""
    system = get_system("cartpole")
    x, u = _points(system, 50, seed=3, scale=2.0)
    _, th, _, thd = x.unbind(-1)
    mc, mp, l, g = 1.0, 0.1, 1.0, 9.81
    den = mc + mp * torch.sin(th) ** 2
    xdd = (u[:, 0] + mp * torch.sin(th) * (l * thd**2 - g * torch.cos(th))) / den
    thdd = (-u[:, 0] * torch.cos(th) - mp * l * thd**2 * torch.cos(th) * torch.sin(th)
            + (mc + mp) * g * torch.sin(th)) / (l * den)
    out = system.true_dynamics(x, u)
    assert torch.allclose(out, torch.stack([x[:, 2], thd, xdd, thdd], -1), atol=1e-12)

    xi = torch.tensor([0.03, 0.05], dtype=F64)
    mp, b = 0.1 + 0.03, 0.05
    mass = torch.stack([torch.stack([torch.full_like(th, mc + mp), mp * l * torch.cos(th)], -1),
                        torch.stack([mp * l * torch.cos(th), torch.full_like(th, mp * l * l)], -1)], -2)
    forces = torch.stack([u[:, 0] + mp * l * torch.sin(th) * thd**2, mp * g * l * torch.sin(th) - b * thd], -1)
    qdd = torch.linalg.solve(mass, forces)
    assert torch.allclose(system.true_dynamics(x, u, xi)[:, 2:], qdd, atol=1e-10)


def test_quadrotor_equations_in_si_units():
    system = get_system("quadrotor2d")
    x, u = _points(system, 50, seed=4)
    th = x[:, 2]
    m, inertia, arm, g = 0.486, 0.00383, 0.25, 9.81
    expected = torch.stack([x[:, 3], x[:, 4], x[:, 5], -torch.sin(th) * u.sum(-1) / m,
                            torch.cos(th) * u.sum(-1) / m - g, arm * (u[:, 0] - u[:, 1]) / inertia], -1)
    assert torch.allclose(system.true_dynamics(x, u), expected, atol=1e-10)
    shifted = system.true_dynamics(x, u, torch.tensor([0.8, -2.5], dtype=F64))
    assert torch.allclose(shifted[:, 5], (arm - 0.025) * (u[:, 0] - u[:, 1]) / (inertia + 0.0008), atol=1e-10)


@pytest.mark.parametrize("name", NAMES)
def test_design_model_is_exact_at_nominal_and_first_order_in_xi(name):
    system = get_system(name)
    x, u = _points(system, 40, seed=5)
    f, w = _design(system, x, u)
    assert torch.allclose(f, system.true_dynamics(x, u), atol=1e-12)
    xi = torch.tensor(system.test_xi, dtype=F64)
    errors = []
    for t in (1.0, 0.1, 0.01):
        design = f + (w @ (t * xi)[:, None])[..., 0]
        errors.append(float((system.true_dynamics(x, u, t * xi) - design).abs().max()))
    assert errors[0] > 0  # the pole mass / the inertia enter nonlinearly: W is the linearisation at the nominal
    assert errors[1] < 0.02 * errors[0] and errors[2] < 0.02 * errors[1]  # second-order remainder
    # W agrees with central differences of the true model in each uncertain parameter
    for j in range(system.k):
        e = torch.zeros(system.k, dtype=F64)
        e[j] = 1e-6
        fd = (system.true_dynamics(x, u, e) - system.true_dynamics(x, u, -e)) / 2e-6
        assert torch.allclose(w[:, :, j], fd, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("name, affine", [("cartpole", 1), ("quadrotor2d", 1)])
def test_design_model_is_exact_along_an_affine_parameter(name, affine):
    """The damping (cart-pole) and the arm length (quadrotor) enter affinely: f + W xi is exact along them."""
    system = get_system(name)
    x, u = _points(system, 30, seed=6)
    f, w = _design(system, x, u)
    xi = torch.zeros(system.k, dtype=F64)
    xi[affine] = system.test_xi[affine]
    assert torch.allclose(system.true_dynamics(x, u, xi), f + (w @ xi[:, None])[..., 0], atol=1e-10)


@pytest.mark.parametrize("name", NAMES)
def test_interval_enclosure_of_the_dynamics_contains_sampled_values(name):
    system = get_system(name)
    centres, u_centres = _points(system, 16, seed=7)
    lo_box, hi_box = (torch.tensor(b, dtype=F64) for b in system.state_box)
    ulo, uhi = (torch.tensor(b, dtype=F64) for b in system.input_box)
    rad = 0.05 * (hi_box - lo_box)
    urad = 0.05 * (uhi - ulo)
    xi_lo = torch.tensor(system.test_xi, dtype=F64) * 0.0
    xi_hi = torch.tensor(system.test_xi, dtype=F64)
    xi_box = Interval(torch.minimum(xi_lo, xi_hi), torch.maximum(xi_lo, xi_hi))
    x_box = Interval(centres - rad, centres + rad)
    u_box = Interval(u_centres - urad, u_centres + urad)
    out = system.dynamics(x_box, u_box, system.params(xi_box, x_box))
    nominal = system.true_dynamics(x_box, u_box)
    gen = torch.Generator().manual_seed(8)
    for _ in range(50):
        x = centres + rad * (2 * torch.rand(centres.shape, generator=gen, dtype=F64) - 1)
        u = u_centres + urad * (2 * torch.rand(u_centres.shape, generator=gen, dtype=F64) - 1)
        t = torch.rand(1, generator=gen, dtype=F64)
        value = system.true_dynamics(x, u, t * xi_hi)
        assert bool(out.contains(value).all())
        assert bool(nominal.contains(system.true_dynamics(x, u)).all())
    # corners of the boxes (sin, cos and the division at their extremes)
    for sx in (-1.0, 1.0):
        for su in (-1.0, 1.0):
            value = system.true_dynamics(centres + sx * rad, u_centres + su * urad, xi_hi)
            assert bool(out.contains(value).all())
    assert bool(torch.isfinite(out.lo).all() and torch.isfinite(out.hi).all())


@pytest.mark.parametrize("name", NAMES)
def test_weighted_design_on_enclosures_contains_point_values(name):
    """The verifier's forward-mode path (parameter derivatives on dual numbers) is sound on these systems."""
    system = get_system(name)
    centres, u_centres = _points(system, 8, seed=9)
    lo_box, hi_box = (torch.tensor(b, dtype=F64) for b in system.state_box)
    rad = 0.02 * (hi_box - lo_box)
    gv = torch.randn(8, system.n, generator=torch.Generator().manual_seed(10), dtype=F64)
    gv_rad = 0.01 * gv.abs()
    gf_box, gw_box = system.weighted_design(Interval(centres - rad, centres + rad), Interval.const(u_centres),
                                            Interval(gv - gv_rad, gv + gv_rad))
    gen = torch.Generator().manual_seed(11)
    for _ in range(30):
        x = centres + rad * (2 * torch.rand(centres.shape, generator=gen, dtype=F64) - 1)
        g = gv + gv_rad * (2 * torch.rand(gv.shape, generator=gen, dtype=F64) - 1)
        gf, gw = system.weighted_design(x, u_centres, g)
        assert bool(gf_box.contains(gf).all()) and bool(gw_box.contains(gw).all())


@pytest.mark.parametrize("name", NAMES)
def test_lqr_stabilises_small_initial_states_on_the_true_model(name):
    system = get_system(name)
    design = lqr_design(system)
    assert max(e.real for e in design.closed_loop_eigenvalues) < 0
    a, b, p, q, r = design.A, design.B, design.P, design.Q, design.R
    residual = a.T @ p + p @ a - p @ b @ torch.linalg.solve(r, b.T @ p) + q
    assert residual.abs().max() < 1e-8 * max(1.0, float(p.abs().max()))
    x0 = initial_states(system, 40, torch.Generator().manual_seed(12)) * 0.3
    for xi in (None, torch.tensor(system.test_xi, dtype=F64)):
        result = evaluate(system, design.controller, x0, xi, lyapunov=design.certificate, horizon=8.0)
        assert result["success_rate"] == 1.0, (xi, result["final_distance"])


def test_linearisations_by_hand():
    """A, B at the equilibrium: the textbook linearisations."""
    from drlyap.lqr import linearize

    a, b = linearize(get_system("cartpole"))
    mc, mp, l, g = 1.0, 0.1, 1.0, 9.81
    a_ref = torch.zeros(4, 4, dtype=F64)
    a_ref[0, 2] = a_ref[1, 3] = 1.0
    a_ref[2, 1] = -mp * g / mc
    a_ref[3, 1] = (mc + mp) * g / (l * mc)
    assert torch.allclose(a, a_ref, atol=1e-12)
    assert torch.allclose(b[:, 0], torch.tensor([0.0, 0.0, 1 / mc, -1 / (l * mc)], dtype=F64), atol=1e-12)
    a, b = linearize(get_system("quadrotor2d"))
    m, inertia, arm = 0.486, 0.00383, 0.25
    assert a[3, 2].item() == pytest.approx(-9.81, rel=1e-12)  # -sin'(0) (2 u*) / m = -g
    assert torch.allclose(b[4], torch.tensor([1 / m, 1 / m], dtype=F64))
    assert torch.allclose(b[5], torch.tensor([arm / inertia, -arm / inertia], dtype=F64))
    assert math.isclose(float(a.abs().sum()), 3 + 9.81, rel_tol=1e-12)
