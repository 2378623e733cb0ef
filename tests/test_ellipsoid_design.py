"""The largest invariant ellipsoid of the linearisations (drlyap.lmi), its warm start, and the face states that find
where V is least on the box's faces."""

import math

import pytest
import torch

from drlyap.closed_loop import ClosedLoop
from drlyap.lmi import ellipsoid_share, invariant_ellipsoid
from drlyap.lqr import linearize, lqr_design
from drlyap.regions import Region
from drlyap.systems import cartpole, quadrotor2d
from drlyap.training import TrainConfig, TrainSections
from drlyap.training.states import descend_on_faces
from drlyap.training.warm_start import Regression, warm_start_pair


def _half(system):
    lo, hi = system.local_box()
    return torch.minimum(-lo, hi)


def _room(system):
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in system.input_box)
    u_star = torch.tensor(system.equilibrium_input, dtype=torch.float64)
    return torch.minimum(u_star - lo, hi - u_star)


@pytest.fixture(scope="module")
def cart_design():
    system = cartpole()
    xi = system.sample_xi(3, torch.Generator().manual_seed(0))
    return system, xi, invariant_ellipsoid(system, xi, rate=0.3)


def test_the_ellipsoid_decays_at_its_rate_for_every_linearisation(cart_design):
    system, xi, design = cart_design
    p, k = design.P, design.K
    for shift in [None, *xi]:
        a, b = linearize(system, shift)
        closed = a - b @ k
        lyap = closed.T @ p + p @ closed + 0.3 * p
        assert float(torch.linalg.eigvalsh((lyap + lyap.T) / 2).max()) <= 1e-6 * float(torch.linalg.eigvalsh(p).max())


def test_the_ellipsoid_lies_in_the_box_with_no_input_saturating(cart_design):
    system, _, design = cart_design
    q = torch.linalg.inv(design.P)
    # the extreme of z_i and of K_k z over {z' P z <= 1} are sqrt(Q_ii) and sqrt(K_k Q K_k^T)
    assert bool((q.diagonal().sqrt() <= _half(system) * (1 + 1e-6)).all())
    assert bool(((design.K @ q @ design.K.T).diagonal().sqrt() <= _room(system) * (1 + 1e-6)).all())
    # sampled on its boundary too
    g = torch.Generator().manual_seed(1)
    w = torch.randn(20000, system.n, generator=g, dtype=torch.float64)
    z = (w / w.norm(dim=1, keepdim=True)) @ torch.linalg.cholesky(q).T
    assert torch.allclose(((z @ design.P) * z).sum(-1), torch.ones(20000, dtype=torch.float64), atol=1e-8)
    assert bool((z.abs() <= _half(system) * (1 + 1e-6)).all())
    assert bool(((z @ design.K.T).abs() <= _room(system) * (1 + 1e-6)).all())


def test_the_ellipsoid_is_larger_than_the_lqrs_set_that_fits_the_same_constraints(cart_design):
    system, _, design = cart_design
    lqr = lqr_design(system)
    q = torch.linalg.inv(lqr.P)
    # the largest {z' P z <= c} of the LQR inside the box and with no input saturating
    c = min(float((_half(system).square() / q.diagonal()).min()),
            float((_room(system).square() / (lqr.K @ q @ lqr.K.T).diagonal()).min()))
    share_lqr = ellipsoid_share(system, lqr.P / c)
    assert ellipsoid_share(system, design.P) > 1.5 * share_lqr


def test_the_share_of_a_ball_in_its_cube():
    system = quadrotor2d()
    half = _half(system)
    p = torch.diag(1.0 / half.square())  # the ellipsoid inscribed in the box
    assert ellipsoid_share(system, p) == pytest.approx(math.pi ** 3 / 6 / 2 ** 6, rel=1e-12)


def test_a_rate_no_gain_meets_is_refused():
    with pytest.raises(ValueError, match="no linear gain keeps an ellipsoid"):
        invariant_ellipsoid(cartpole(), rate=1e4)
    with pytest.raises(ValueError, match="decay rate"):
        invariant_ellipsoid(cartpole(), rate=float("nan"))


def test_the_ellipsoid_warm_start_sets_the_pair_exactly_just_above_the_faces_level():
    system = cartpole()
    cfg = TrainConfig(system="cartpole", lyapunov_hidden=[8], lyapunov_skip=True, controller_hidden=[8],
                      controller_skip=True, alpha_hat=1e-3, warm_start="ellipsoid").resolved(system)
    plan = TrainSections.of(cfg)
    lyapunov, controller = plan.networks.build(system)
    region = Region.of(system, cfg.delta)
    xi = system.sample_xi(3, torch.Generator().manual_seed(0))
    warm = warm_start_pair(ClosedLoop(system, lyapunov, controller), plan.networks, 1.0, region,
                           torch.Generator().manual_seed(0), xi, 0.3, Regression(cfg.lr))
    design = invariant_ellipsoid(system, xi, 0.3)
    assert warm["method"] == "ellipsoid" and warm["iterations"] == 0 and warm["rate"] == 0.3
    z = region.sample(2000, torch.Generator().manual_seed(1))
    with torch.no_grad():
        v = lyapunov.double()(z)
        assert torch.allclose(v, warm["P_scale"] * ((z @ design.P) * z).sum(-1), rtol=1e-5)
        # the network holds K in float32: each output is exact up to K's rounding times |z|
        rounding = 4 * torch.finfo(torch.float32).eps * (z.abs() @ design.K.abs().T)
        assert ((controller.double().raw(z) + z @ design.K.T).abs() <= rounding).all()
    assert warm["P_scale"] == pytest.approx(1.06, rel=1e-3)  # the ellipsoid meets a face: V = 1.06 there


def test_descent_on_the_faces_finds_the_least_v_of_a_tilted_quadratic():
    from drlyap.networks import QuadraticLyapunov

    system = quadrotor2d()
    region = Region.of(system, 0.1)
    half = region.hi
    m = torch.eye(6, dtype=torch.float64) * 2.0
    m[0, 3] = m[3, 0] = 1.2  # x with xdot, tilted
    m[2, 5] = m[5, 2] = -1.1
    p = m / half[:, None] / half[None, :]
    v = QuadraticLyapunov(p)
    z = region.sample_faces(1024, torch.Generator().manual_seed(0))
    on_face = (z == region.lo) | (z == region.hi)
    for _ in range(300):
        z = descend_on_faces(v, z, region)
    assert bool(((z == region.lo) | (z == region.hi))[on_face].all())  # each state stays on its face
    assert bool(region.contains(z).all())
    # the least V on the face z_i = +-h_i is h_i^2 / (P^-1)_ii
    least = float((half.square() / torch.linalg.inv(p).diagonal()).min())
    with torch.no_grad():
        found = float(v(z).min())
    assert found == pytest.approx(least, rel=1e-3)
    uniform = region.sample_faces(1024, torch.Generator().manual_seed(0))
    with torch.no_grad():
        assert float(v(uniform).min()) > 1.2 * least  # what uniform face states see
