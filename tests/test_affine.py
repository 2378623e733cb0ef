"""Affine forms (first-order Taylor models): soundness against dense sampling, tightness against intervals.

Every test draws points inside random boxes (the corners included) and checks that the enclosure of
each computed value contains the value computed by plain float64 torch code at those points.
"""

import math
from fractions import Fraction

import pytest
import torch

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import DRPointwise, Nominal, TrueDecrease
from drlyap.enclosures import Affine, Dual, Interval, is_enclosure, quadratic_max
from drlyap.enclosures.quadratic import quadratic_span
from drlyap.networks import Controller, Lyapunov, TanhMLP
from drlyap.proof_settings import Budget
from drlyap.regions import Domain, Region
from drlyap.systems import get_system
from drlyap.training import TrainConfig, TrainSections
from drlyap.verification import ProofRules, maximize, verify_condition
from drlyap.verification.bounds import condition_objective
from handmade import linear_pair, small_pendulum

torch.set_num_threads(1)
F64 = torch.float64


def _boxes(count, n, width, seed=0, centre_scale=1.0):
    """``count`` random boxes ``(count, n)`` of the given side widths (a number or ``(n,)``)."""
    gen = torch.Generator().manual_seed(seed)
    width = torch.as_tensor(width, dtype=F64)
    c = (torch.rand(count, n, generator=gen, dtype=F64) * 2 - 1) * centre_scale
    w = width * (0.2 + 0.8 * torch.rand(count, n, generator=gen, dtype=F64))
    return c - w / 2, c + w / 2


def _samples(lo, hi, count=2000, seed=1):
    """Points ``(B, count + 2^n, n)`` in each box: uniform ones and all the corners."""
    gen = torch.Generator().manual_seed(seed)
    b, n = lo.shape
    u = torch.rand(b, count, n, generator=gen, dtype=F64)
    corners = torch.cartesian_prod(*[torch.tensor([0.0, 1.0], dtype=F64)] * n).reshape(-1, n)
    u = torch.cat([u, corners.expand(b, -1, -1)], 1)
    return lo[:, None] + (hi - lo)[:, None] * u


def _flat(fn, pts):
    """``fn`` on points ``(B, S, n)`` as one batch; output ``(B, S, ...)``."""
    b, s, n = pts.shape
    out = fn(pts.reshape(b * s, n))
    return out.reshape(b, s, *out.shape[1:])


def _inside(enc, values):
    """Whether the enclosure ``(B, ...)`` contains every sampled value ``(B, S, ...)``."""
    iv = enc.to_interval()
    return bool(((iv.lo[:, None] <= values) & (values <= iv.hi[:, None])).all())


def _width(enc):
    iv = enc.to_interval()
    return iv.hi - iv.lo


# ----------------------------------------------------------------------------------------- single operations
OPS = {
    "add": lambda z: z[:, 0] + z[:, 1] + 0.1,
    "sub": lambda z: z[:, 0] - z[:, 1] - 0.3,
    "neg": lambda z: -z[:, 0],
    "scalar mul": lambda z: z[:, 0] * 3.7 + 0.1 * z[:, 1],
    "mul": lambda z: z[:, 0] * z[:, 1],
    "mul self": lambda z: (z[:, 0] + z[:, 1]) * (z[:, 0] - 2.0 * z[:, 1]),
    "div": lambda z: z[:, 0] / (z[:, 1] + 4.0),
    "div negative": lambda z: (z[:, 0] + 1.0) / (z[:, 1] - 4.0),
    "reciprocal": lambda z: 1.0 / (z[:, 0] * 0.5 + 2.0),
    "tanh": lambda z: torch.tanh(z[:, 0] * 2.0 + z[:, 1]),
    "sin": lambda z: torch.sin(z[:, 0] * 2.0 - z[:, 1]),
    "cos": lambda z: torch.cos(z[:, 0] + z[:, 1]),
    "exp": lambda z: torch.exp(z[:, 0] - z[:, 1]),
    "sqrt": lambda z: torch.sqrt(z[:, 0] * z[:, 0] + z[:, 1] * z[:, 1]),
    "sqrt shifted": lambda z: torch.sqrt(z[:, 0] + 3.0),
    "square": lambda z: torch.square(z[:, 0] - z[:, 1]),
    "pow": lambda z: (z[:, 0] + 0.2) ** 3,
    "abs": lambda z: torch.abs(z[:, 0] - z[:, 1] * 0.5),
    "linear": lambda z: torch.nn.functional.linear(
        z, torch.tensor([[0.3, -1.1], [2.0, 0.7], [0.1, 0.1]], dtype=F64), torch.tensor([0.2, -0.1, 0.0], dtype=F64)),
    "sum": lambda z: (z * torch.tensor([1.0, -2.0], dtype=F64)).sum(-1),
    "stack unbind": lambda z: torch.stack([z[:, 1], z[:, 0] * z[:, 1], z.unbind(-1)[0]], dim=-1),
    "cat index": lambda z: torch.cat([z[..., :1], z[:, 1:] * 2.0], dim=-1)[:, [1, 0]],
    "norm": lambda z: torch.linalg.vector_norm(z, dim=-1),
    # forms with a quadratic part (one-signed where it comes from a square) entering products and functions
    "mul of squares": lambda z: torch.square(z[:, 0] - z[:, 1]) * (torch.tanh(z[:, 0] + z[:, 1]) + z[:, 0] * z[:, 1]),
    "tanh of square": lambda z: torch.tanh(z[:, 0] * z[:, 0] - z[:, 1]),
    "sin of product": lambda z: torch.sin(z[:, 0] * z[:, 1] + 0.5),
    "exp of square": lambda z: torch.exp(-torch.square(z[:, 0] + 0.3 * z[:, 1])),
    "reciprocal of square": lambda z: 1.0 / (torch.square(z[:, 0]) + z[:, 1] * 0.1 + 2.0),
}


@pytest.mark.parametrize("name", sorted(OPS))
@pytest.mark.parametrize("width", [1e-3, 0.3, 3.0])
def test_each_operation_encloses_sampled_values(name, width):
    fn = OPS[name]
    lo, hi = _boxes(40, 2, width, seed=hash(name) % 1000)
    out = fn(Affine.box(lo, hi))
    assert isinstance(out, Affine)
    assert _inside(out, _flat(fn, _samples(lo, hi))), name


def test_clamp_encloses_and_is_exact_where_inactive():
    low, high = torch.tensor([-0.4, -2.0], dtype=F64), torch.tensor([0.3, 2.0], dtype=F64)

    def fn(z):
        y = torch.nn.functional.linear(z, torch.tensor([[1.0, 0.5], [0.2, -0.3]], dtype=F64))
        return y.clamp(low, high) if is_enclosure(y) else torch.maximum(torch.minimum(y, high), low)

    for width in (0.01, 0.5, 3.0):
        lo, hi = _boxes(60, 2, width, seed=3)
        out = fn(Affine.box(lo, hi))
        assert _inside(out, _flat(fn, _samples(lo, hi)))
    # the second output never saturates on these boxes: the identity, with no added remainder beyond rounding
    assert float((out.r.hi - out.r.lo)[:, 1].max()) < 1e-12


def test_linear_operations_keep_correlations_exactly():
    lo, hi = _boxes(10, 3, 0.5)
    z = Affine.box(lo, hi)
    x, y, w = z.unbind(-1)
    assert float(_width(x - x).max()) < 1e-13
    assert float(_width((x + y) * 2.0 - y - x - x - y).max()) < 1e-12
    # sin(x)^2 + cos(x)^2 on a narrow box is close to a constant: only the linearisation errors remain
    narrow_lo, narrow_hi = _boxes(10, 1, 1e-4)
    t = Affine.box(narrow_lo, narrow_hi)[:, 0]
    assert float(_width(torch.sin(t).square() + torch.cos(t).square()).max()) < 1e-7


def test_outward_rounding_against_exact_rationals():
    """Sums and products of values that are not representable: the enclosure contains the exact value."""
    lo = torch.tensor([[0.1, 0.2, 1 / 3]], dtype=F64)
    z = Affine.box(lo, lo)  # point boxes: the rounding pads are the only width
    x, y, w = z.unbind(-1)
    out = ((x + y) * w - x * 0.7 + y / 3.0).to_interval()
    fx, fy, fw = (Fraction(float(v)) for v in lo[0])
    exact = (fx + fy) * fw - fx * Fraction(0.7) + fy / 3
    assert Fraction(float(out.lo[0])) <= exact <= Fraction(float(out.hi[0]))
    assert float(out.hi[0] - out.lo[0]) < 1e-14


def test_interval_and_affine_mix_and_batches_do_not():
    lo, hi = _boxes(5, 2, 0.2)
    z = Affine.box(lo, hi)
    mixed = z[:, 0] * Interval(lo[:, 1], hi[:, 1]) + Interval.const(torch.ones(5, dtype=F64))
    assert isinstance(mixed, Affine)
    pts = _samples(lo, hi)
    assert _inside(mixed, pts[..., 0] * pts[..., 1] + 1.0)
    assert isinstance(torch.stack([z[:, 0], Interval(lo[:, 1], hi[:, 1])], -1), Affine)
    with pytest.raises(ValueError, match="different boxes"):
        z[:, 0].sum(0)
    with pytest.raises(ValueError, match="different boxes"):
        z[:1, 0] + z[:, 1]
    with pytest.raises(ValueError, match="contains 0"):
        1.0 / Affine.box(-torch.ones(2, 1, dtype=F64), torch.ones(2, 1, dtype=F64))



def test_quadratic_part_keeps_products_of_linear_parts():
    """``x * y`` keeps ``Lx Ly`` as a quadratic part: sums of products cancel before they are bounded."""
    lo, hi = _boxes(30, 4, 0.4, seed=5)
    z = Affine.box(lo, hi)
    a, b, c, d = z.unbind(-1)
    assert float(_width(a * b - b * a).max()) < 1e-12
    dot = a * c + b * d - (c * a + d * b)
    assert float(_width(dot).max()) < 1e-12
    # (a + b)^2 - a^2 - 2 a b - b^2 is 0: only rounding remains
    assert float(_width((a + b).square() - a.square() - a * b * 2.0 - b.square()).max()) < 1e-11
    q = (a * b).q
    assert q is not None and torch.allclose(q, q.transpose(-1, -2))  # kept symmetric


@pytest.mark.parametrize("k", [2, 4, 6])
def test_range_of_the_quadratic_part_encloses_corners_and_samples(k):
    gen = torch.Generator().manual_seed(k)
    q = torch.randn(50, k, k, generator=gen, dtype=F64)
    q = (q + q.transpose(-1, -2)) / 2
    form = Affine(torch.zeros(50, dtype=F64), None, None, q)
    rng = form._quad()
    e = torch.cat([torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64)] * k).reshape(-1, k),
                   torch.rand(3000, k, generator=gen, dtype=F64) * 2 - 1])
    values = torch.einsum("sk,bkl,sl->bs", e, q, e)
    assert bool((rng.lo[:, None] <= values).all() and (values <= rng.hi[:, None]).all())
    assert _inside(form, values)



@pytest.mark.parametrize("k", [2, 3, 6])
def test_joint_bound_is_sound_and_tight_for_stiff_concave_quadratics(k):
    """A concave q curved 1e4 times more along mixed directions than along others (a stiff closed loop's Vdot near
    x*): the linear part's growth is cancelled by the curvature, which the vertex bound alone cannot see."""
    gen = torch.Generator().manual_seed(20 + k)
    basis = torch.linalg.qr(torch.randn(80, k, k, generator=gen, dtype=F64))[0]
    curv = torch.ones(80, k, dtype=F64)
    curv[:, 0] = 1e4
    q = -(basis * curv[:, None, :]) @ basis.mT
    q = (q + q.mT) / 2
    q[::4] += torch.diag_embed(torch.rand(20, k, generator=gen, dtype=F64))  # some indefinite ones too
    g = torch.randn(80, k, generator=gen, dtype=F64) * 30
    e = torch.cat([torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64)] * k).reshape(-1, k),
                   torch.rand(20000, k, generator=gen, dtype=F64) * 2 - 1])
    values = (g @ e.T + torch.einsum("sk,bkl,sl->bs", e, q, e)).amax(-1)
    bound = quadratic_max(g, q)
    assert bool((values <= bound).all())
    # the concave ones: at most the larger of the sampled maximum and the unconstrained one, plus 0.2 per symbol
    # (term by term: the off-diagonal curvature alone is ~1e3-1e4 here)
    concave = torch.ones(80, dtype=torch.bool)
    concave[::4] = False
    top = 0.25 * (g.unsqueeze(-2) @ torch.linalg.solve(-q, g.unsqueeze(-1)))[..., 0, 0]
    assert bool((bound[concave] <= torch.maximum(top[concave], values[concave]) + 0.2 * k + 1e-9).all())
    assert not bool(torch.isfinite(quadratic_max(g[:1], torch.full_like(q[:1], math.nan))).any())


@pytest.mark.parametrize("k", [2, 4, 6])
def test_joint_bound_of_linear_and_quadratic_parts_is_sound_and_exact_for_convex_diagonals(k):
    gen = torch.Generator().manual_seed(10 + k)
    g = torch.randn(60, k, generator=gen, dtype=F64)
    q = torch.randn(60, k, k, generator=gen, dtype=F64)
    q = (q + q.transpose(-1, -2)) / 2
    e = torch.cat([torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64)] * k).reshape(-1, k),
                   torch.rand(5000, k, generator=gen, dtype=F64) * 2 - 1])
    values = g @ e.T + torch.einsum("sk,bkl,sl->bs", e, q, e)
    bound = quadratic_max(g, q)
    assert bool((values.amax(-1) <= bound).all())
    convex = q + torch.diag_embed(q.abs().sum(-1))  # diagonally dominant: the maximum is at a vertex
    vals = g @ e.T + torch.einsum("sk,bkl,sl->bs", e, convex, e)
    assert torch.allclose(quadratic_max(g, convex), vals.amax(-1), rtol=1e-9)
    lo, hi = quadratic_span(g, q)  # both sides at once: the negation's bound from the same eigendecomposition
    assert torch.equal(hi, bound) and bool((lo >= -quadratic_max(-g, -q)).all())  # and the convex minimum's
    form = Affine(torch.zeros(60, dtype=F64), g, None, q)
    tight, loose = form.tight_interval(), form.to_interval()
    assert bool((tight.lo <= values.amin(-1)).all() and (values.amax(-1) <= tight.hi).all())
    assert bool((tight.hi - tight.lo <= loose.hi - loose.lo).all())

@pytest.mark.parametrize("k", [2, 4, 6])
def test_the_minimum_of_a_convex_quadratic_on_a_face_of_the_cube_is_bounded_tightly(k):
    """Where a box straddles a sublevel set's boundary, V's minimum over it sits on a face: the vertex and dual bounds
    are loose there; the convexity bound is sound for any q (shifted by its least eigenvalue) and exact for a
    semidefinite one."""
    gen = torch.Generator().manual_seed(20 + k)
    a = torch.randn(80, k, k, generator=gen, dtype=F64)
    psd = a @ a.mT  # convex
    indefinite = torch.randn(80, k, k, generator=gen, dtype=F64)
    g = 6 * torch.randn(80, k, generator=gen, dtype=F64)  # the unconstrained minimiser mostly outside the cube
    e = torch.cat([torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64)] * k).reshape(-1, k),
                   torch.rand(20000, k, generator=gen, dtype=F64) * 2 - 1])
    for q in (psd, (indefinite + indefinite.mT) / 2):
        lo, _ = quadratic_span(g, q)
        values = g @ e.T + torch.einsum("sk,bkl,sl->bs", e, q, e)
        assert bool((lo <= values.amin(-1)).all())
    # exact for the convex one: the true minimum by projected gradient descent from many starts
    x = torch.rand(80, 64, k, generator=gen, dtype=F64) * 2 - 1
    step = 1 / (2 * torch.linalg.eigvalsh(psd)[:, -1])
    for _ in range(3000):
        x = (x - step[:, None, None] * (g[:, None] + 2 * x @ psd)).clamp(-1, 1)
    best = ((g[:, None] * x).sum(-1) + torch.einsum("bsk,bkl,bsl->bs", x, psd, x)).amin(-1)
    lo, _ = quadratic_span(g, psd)
    assert bool((lo <= best).all())
    exact = torch.isclose(lo, best, rtol=1e-8, atol=1e-8 * float(psd.abs().max()))  # where its search found the minimum
    assert float(exact.double().mean()) >= 0.9
    lo, _ = quadratic_span(g[:1], torch.full_like(psd[:1], math.nan))
    assert not bool(torch.isfinite(lo).any())


def test_a_joint_bound_asked_for_some_lower_ends_keeps_every_upper_end():
    """The verifier reads the lower end of V alone (not of the condition's components): the entries whose lower end is
    not asked keep the plain interval's, the asked ones and every upper end are the same bits as the full bound's."""
    gen = torch.Generator().manual_seed(3)
    g = torch.randn(40, 5, 6, generator=gen, dtype=F64)
    q = torch.randn(40, 5, 6, 6, generator=gen, dtype=F64)
    form = Affine(torch.randn(40, 5, generator=gen, dtype=F64), g, Interval.const(torch.zeros(40, 5, dtype=F64)),
                  (q + q.transpose(-1, -2)) / 2)
    full, plain = form.tight_interval(), form.to_interval()
    for asked in (slice(-1, None), slice(0, 0), slice(1, 3)):
        some = form.tight_interval(lower=asked)
        assert torch.equal(some.hi, full.hi)
        read = torch.zeros(5, dtype=torch.bool)
        read[asked] = True
        assert torch.equal(some.lo[:, read], full.lo[:, read])
        assert torch.equal(some.lo[:, ~read], plain.lo[:, ~read])


@pytest.mark.parametrize("name", ["tanh", "sin", "cos", "exp", "reciprocal"])
def test_second_order_functions_leave_a_third_order_remainder(name):
    """On narrow boxes the remainder (beyond the exact linear and quadratic parts) shrinks like width^3."""
    fn = OPS[name]
    widths = []
    for width in (0.02, 0.01):
        lo, hi = _boxes(20, 2, width, seed=4)
        out = fn(Affine.box(lo, hi))
        assert _inside(out, _flat(fn, _samples(lo, hi, count=500)))
        assert out.q is not None
        widths.append(float((out.r.hi - out.r.lo).max()))
    assert widths[1] < widths[0] / 5, widths  # third order: 8x; a first-order remainder would shrink 4x


def test_wide_inputs_fall_back_to_the_secant_form():
    """On wide ranges the Taylor remainder would exceed the secant's error: the first-order form is kept."""
    lo, hi = _boxes(20, 2, 4.0, seed=6)
    fn = OPS["tanh"]
    out = fn(Affine.box(lo, hi))
    assert _inside(out, _flat(fn, _samples(lo, hi)))
    assert float((out.r.hi - out.r.lo).max()) <= 2.0 + 1e-9  # the secant's error; the Taylor remainder is ~100

# ----------------------------------------------------------------------------------------- networks
def _small_networks(n, seed=0, hidden=(16, 16), gain=0.7):
    torch.manual_seed(seed)
    scale = [1.0] * n
    lyap = Lyapunov(n, hidden, 4, 0.5, scale).double()
    ctrl = Controller(n, ([-2.0], [2.0]), [0.0], hidden, 3.0, scale).double()
    for net in (lyap, ctrl):
        with torch.no_grad():
            for p in net.parameters():
                p.mul_(gain)
    return lyap, ctrl


@pytest.mark.parametrize("n", [2, 4, 6])
def test_tanh_network_value_gradient_and_controller_are_enclosed(n):
    lyap, ctrl = _small_networks(n, seed=n)
    mlp = TanhMLP([n, 12, 12, 3]).double()
    for width in (0.02, 0.3):
        lo, hi = _boxes(30, n, width, seed=n)
        pts = _samples(lo, hi, count=1000)
        z = Affine.box(lo, hi)
        with torch.no_grad():
            assert _inside(mlp(z), _flat(mlp, pts))
            v, g = lyap.value_and_grad(z)
            assert _inside(v, _flat(lambda x: lyap.value_and_grad(x)[0], pts))
            assert _inside(g, _flat(lambda x: lyap.value_and_grad(x)[1], pts))
            assert _inside(ctrl(z), _flat(ctrl, pts))


def test_dual_over_affine_encloses_sampled_gradients():
    n = 4
    lyap, ctrl = _small_networks(n, seed=7)
    lo, hi = _boxes(20, n, 0.1, seed=7)
    pts = _samples(lo, hi, count=500)
    eye = torch.eye(n, dtype=F64).expand(20, n, n)
    z = Dual(Affine.box(lo, hi), Interval(eye, eye))
    out = lyap(z)
    assert isinstance(out.v, Affine) and isinstance(out.d, Affine)
    x = pts.reshape(-1, n).clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(lyap(x).sum(), x)
    assert _inside(out.v, _flat(lambda p: lyap(p).detach(), pts))
    assert _inside(out.d, grad.reshape(20, -1, n))
    # the manual gradient (what the conditions use) agrees with the dual one within both enclosures
    _, g = lyap.value_and_grad(Affine.box(lo, hi))
    both = torch.maximum(out.d.lo, g.lo) <= torch.minimum(out.d.hi, g.hi)
    assert bool(both.all())
    # first-order duals through the controller's clamp (the saturated and the free case)
    u = ctrl(z)
    (gu,) = torch.autograd.grad(ctrl(x).sum(), x)
    assert _inside(u.v, _flat(lambda p: ctrl(p).detach(), pts))
    assert _inside(u.d[:, 0], gu.reshape(20, -1, n))


# ----------------------------------------------------------------------------------------- systems
@pytest.mark.parametrize("name", ["cartpole", "quadrotor2d"])
def test_dynamics_on_random_small_boxes_enclose_sampled_values(name):
    system = get_system(name)
    n, m = system.n, system.m
    slo, shi = (torch.tensor(b, dtype=F64) for b in system.state_box)
    ulo, uhi = (torch.tensor(b, dtype=F64) for b in system.input_box)
    span = torch.cat([shi - slo, uhi - ulo])
    base = torch.cat([slo, ulo])
    gen = torch.Generator().manual_seed(0)
    centre = base + span * torch.rand(40, n + m, generator=gen, dtype=F64)
    half = span * 0.02 * torch.rand(40, n + m, generator=gen, dtype=F64)
    lo, hi = centre - half, centre + half
    pts = _samples(lo, hi, count=1000)
    box = Affine.box(lo, hi)
    xi = torch.tensor(system.test_xi, dtype=F64)
    out = system.true_dynamics(box[:, :n], box[:, n:], xi)
    assert isinstance(out, Affine) and tuple(out.shape) == (40, n)
    assert _inside(out, _flat(lambda p: system.true_dynamics(p[:, :n], p[:, n:], xi), pts))
    # the design model's forward-mode parameter derivatives run on Dual(Affine)
    cov = torch.randn(n, generator=gen, dtype=F64).expand(40, n)
    s, w = system.weighted_design(box[:, :n], box[:, n:], Interval.const(cov))
    fs, ws = [], []
    for p in pts.unbind(1):
        a, b = system.weighted_design(p[:, :n], p[:, n:], cov)
        fs.append(a)
        ws.append(b)
    assert _inside(s, torch.stack(fs, 1))
    assert _inside(w, torch.stack(ws, 1))


@pytest.mark.parametrize("name", ["cartpole", "quadrotor2d"])
def test_decrease_condition_objective_on_affine_boxes(name):
    system = get_system(name)
    torch.manual_seed(1)
    lyap, ctrl = TrainSections.of(TrainConfig(system=name).resolved(system)).networks.build(system)
    xi = system.sample_xi(3, torch.Generator().manual_seed(0))
    slo, shi = system.local_box()
    lo, hi = _boxes(16, system.n, 0.03 * (shi - slo), seed=2)
    lo, hi = lo * (shi - slo) / 2, hi * (shi - slo) / 2  # centres spread over the state box
    lo, hi = torch.minimum(lo, hi), torch.maximum(lo, hi)
    pts = _samples(lo, hi, count=300)
    for cond in (Nominal(xi.mean(0, keepdim=True), 0.1), DRPointwise(0.01, 0.2, xi, 0.1),
                 TrueDecrease(torch.tensor([system.test_xi], dtype=F64), 0.1)):
        out = condition_objective(ClosedLoop(system, lyap, ctrl), cond)(Affine.box(lo, hi))
        with torch.no_grad():
            values = _flat(lambda p, c=cond: c.components(c.terms(ClosedLoop(system, lyap.double(), ctrl.double()), p)), pts)
        assert _inside(out, values), cond.label


# ----------------------------------------------------------------------------------------- tightness
@pytest.mark.parametrize("n", [2, 4, 6])
def test_affine_is_tighter_than_intervals_on_networks(n):
    lyap, _ = _small_networks(n, seed=11, hidden=(32, 32), gain=1.0)  # torch's default initialisation
    lo, hi = _boxes(40, n, 0.2, seed=n)
    with torch.no_grad():
        vi, gi = lyap.value_and_grad(Interval(lo, hi))
        va, ga = lyap.value_and_grad(Affine.box(lo, hi))
    ratio_v = float(((vi.hi - vi.lo) / _width(va)).median())
    ratio_g = float(((gi.hi - gi.lo) / _width(ga)).median())
    print(f"n={n}: interval / affine width, median over boxes: V {ratio_v:.1f}x, grad V {ratio_g:.1f}x")
    assert bool((_width(va) <= (vi.hi - vi.lo) * 1.01).all())
    assert ratio_v > 2.0, ratio_v
    assert ratio_g > 10.0, ratio_g


# ----------------------------------------------------------------------------------------- branch and bound
XI = torch.tensor([[0.05, 0.02], [-0.02, -0.01], [0.08, 0.03]], dtype=F64)


def _pendulum_region_points(system, delta, per=120):
    lo, hi = system.local_box()
    axes = [lo[i] + (hi[i] - lo[i]) * (torch.arange(per, dtype=F64) + 0.5) / per for i in range(system.n)]
    z = torch.cat([torch.cartesian_prod(*axes),
                   lo + (hi - lo) * torch.rand(20000, system.n, generator=torch.Generator().manual_seed(3), dtype=F64)])
    return z[z.norm(dim=-1) >= delta]


def test_branch_and_bound_with_affine_forms_verifies_with_fewer_boxes():
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    spec = DRPointwise(1e-3, 0.1, XI, 0.05)
    loop, region = ClosedLoop(system, lyap, ctrl), Region.of(system, 0.2)
    mv = verify_condition(loop, spec, region, Budget(seconds=20, enclosure="mean-value"))
    af = verify_condition(loop, spec, region, Budget(seconds=20, enclosure="affine"))
    assert mv.status == af.status == "verified"
    assert af.boxes_processed <= mv.boxes_processed
    assert float(ClosedLoop(system, lyap, ctrl).exact(spec, _pendulum_region_points(system, 0.2)).max()) <= 0
    with pytest.raises(ValueError, match="unknown enclosure"):
        Budget(enclosure="taylor")


def test_branch_and_bound_with_affine_forms_leaves_every_violation_unverified():
    system = small_pendulum(((-1.5, -3.0), (1.5, 3.0)))
    lyap, ctrl = linear_pair(system)
    spec = DRPointwise(1e-3, 0.1, XI, 0.05)
    result = verify_condition(ClosedLoop(system, lyap, ctrl), spec, Region.of(system, 0.2),
                              Budget(seconds=20, min_width=1e-2, enclosure="affine"), rules=ProofRules(keep_boxes=10**6))
    z = _pendulum_region_points(system, 0.2, per=150)
    bad = z[ClosedLoop(system, lyap, ctrl).exact(spec, z) > 0]
    assert bad.shape[0] and result.status == "violated" and 0 < result.verified_fraction < 1
    lo = torch.tensor([b["lo"] for b in result.unverified_boxes], dtype=F64).reshape(-1, 2)
    hi = torch.tensor([b["hi"] for b in result.unverified_boxes], dtype=F64).reshape(-1, 2)
    covered = ((lo[None] <= bad[:, None]) & (bad[:, None] <= hi[None])).all(-1).any(-1)
    assert bool(covered.all()), bad[~covered]


def test_maximize_with_affine_forms_bounds_sampled_values_at_4_states():
    system = get_system("cartpole")
    torch.manual_seed(5)
    lyap, ctrl = TrainSections.of(TrainConfig(system="cartpole").resolved(system)).networks.build(system)
    spec = Nominal(torch.zeros(1, system.k, dtype=F64), 0.1)
    lo, hi = system.local_box()
    lo, hi = lo * 0.3, hi * 0.3
    lower, upper, info = maximize(condition_objective(ClosedLoop(system, lyap, ctrl), spec),
                                  Domain(lo[None], hi[None], (hi - lo) / 2),
                                  Budget(seconds=3.0, boxes=1_000_000, enclosure="affine"))
    z = lo + (hi - lo) * torch.rand(20000, system.n, generator=torch.Generator().manual_seed(0), dtype=F64)
    sampled = float(ClosedLoop(system, lyap, ctrl).exact(spec, z).max())
    assert float(lower[0]) <= float(upper[0])
    assert sampled <= float(upper[0]), (sampled, float(upper[0]), info)


def test_maximize_stopped_early_keeps_a_sound_finite_bound():
    """Stopped with more boxes queued than it re-bounds, the upper bound comes from their parents' bounds:
    finite, above every sampled value, and tighter than the first box's."""
    def objective(z):  # (B, 2) -> (B, 1): sin(3 z1) cos(2 z2) + z1 z2
        return (torch.sin(3 * z[:, :1]) * torch.cos(2 * z[:, 1:]) + z[:, :1] * z[:, 1:])

    lo, hi = torch.tensor([[-1.0, -1.0]], dtype=F64), torch.tensor([[1.0, 1.0]], dtype=F64)
    scale = torch.tensor([2.0, 2.0], dtype=F64)
    first = maximize(objective, Domain(lo, hi, scale), Budget(seconds=2.0, boxes=1, batch=1, enclosure="mean-value"))[1]
    lower, upper, info = maximize(objective, Domain(lo, hi, scale),
                                  Budget(seconds=2.0, boxes=60, batch=2, enclosure="mean-value"),
                                  rel_tol=1e-9)
    assert info.stopped == "box budget"
    z = lo + (hi - lo) * torch.rand(50000, 2, generator=torch.Generator().manual_seed(1), dtype=F64)
    assert float(objective(z).max()) <= float(upper[0]) < float(first[0]) < math.inf
    assert float(lower[0]) <= float(upper[0])


def test_maximize_refines_until_a_centre_is_accepted():
    """Where no starting centre is accepted (``centre_ok``), the boxes are split until one is, not closed at their
    first bound: the bracket then closes on the largest value over the accepted part."""
    def objective(z):  # (B, 2) -> (B, 1): -(z1 - 0.9)^2 - z2^2, largest at (0.9, 0)
        return -(z[:, :1] - 0.9).square() - z[:, 1:].square()

    lo, hi = torch.tensor([[0.0, -1.0]], dtype=F64), torch.tensor([[1.0, 1.0]], dtype=F64)
    scale = torch.tensor([1.0, 2.0], dtype=F64)
    lower, upper, info = maximize(objective, Domain(lo, hi, scale, contains=lambda z: z[:, 0] > 0.7),
                                  Budget(seconds=30.0, boxes=4000, enclosure="mean-value"), rel_tol=1e-9, abs_tol=1e-4)
    assert info.attained_at is not None and float(info.attained_at[0, 0]) > 0.7
    assert float(lower[0]) <= 0.0 <= float(upper[0]) and float(upper[0]) - float(lower[0]) < 1e-3


def test_a_box_is_bounded_the_same_whatever_is_bounded_beside_it():
    """Each entry picks its own form of a function (second order, or the secant where its input is wide), so a box's
    bound does not depend on the other boxes of its batch, which the number of workers changes (a narrow box beside
    wide ones was bounded tighter than alone: 1e-2 of its width on the cart-pole)."""
    torch.manual_seed(0)
    net = TanhMLP([4, 16, 16, 3]).double()
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.mul_(3.0)
    g = torch.Generator().manual_seed(1)
    centre = torch.rand(1, 4, generator=g, dtype=torch.float64)
    narrow_lo, narrow_hi = centre - 0.1, centre + 0.1
    wide_c = torch.rand(63, 4, generator=g, dtype=torch.float64) * 4 - 2
    lo, hi = torch.cat([narrow_lo, wide_c - 1.5]), torch.cat([narrow_hi, wide_c + 1.5])
    alone = net(Affine.box(narrow_lo, narrow_hi)).to_interval()
    beside = net(Affine.box(lo, hi)).to_interval()
    # the same form (matrix products of other shapes may round the last bit differently: both are outward rounded)
    assert torch.allclose(alone.lo[0], beside.lo[0], rtol=0, atol=1e-12)
    assert torch.allclose(alone.hi[0], beside.hi[0], rtol=0, atol=1e-12)
    pts = narrow_lo + (narrow_hi - narrow_lo) * torch.rand(2000, 4, generator=g, dtype=torch.float64)
    values = net(pts)
    assert bool((values >= alone.lo[0]).all() and (values <= alone.hi[0]).all())


def test_a_products_one_signed_higher_part_is_centred_first():
    """``x = L^2`` (its quadratic part ranges over [0, a]) times a linear ``y``: written about the centre of that
    range, the product's remainder is ``[-a/2, a/2] * dev(y)`` instead of ``[0, a] * dev(y)``: half as wide."""
    lo, hi = _boxes(30, 2, 0.2, seed=3)
    centre = (lo + hi) / 2
    lo, hi = lo - centre, hi - centre  # L = z0 - z1 is centred at 0: x has no linear part
    z = Affine.box(lo, hi)
    x, y = torch.square(z[:, 0] - z[:, 1]), z[:, 0] + 2.0 * z[:, 1]
    a = x._quad().hi - x._quad().lo
    out = x * y
    assert _inside(out, _flat(lambda t: torch.square(t[:, 0] - t[:, 1]) * (t[:, 0] + 2.0 * t[:, 1]),
                              _samples(lo, hi)))
    assert bool(((out.r.hi - out.r.lo) <= 1.05 * a * y._lin()).all())


def test_a_form_with_an_unbounded_remainder_gives_no_finite_range():
    """Centring the factors of a product must not turn an unbounded remainder into a finite range."""
    lo, hi = _boxes(4, 2, 0.2, seed=5)
    z = Affine.box(lo, hi)
    inf = torch.full((4,), float("inf"), dtype=F64)
    x = Affine(z.c[:, 0], z.g[:, 0], Interval(-inf, inf))
    for out in (x * z[:, 1], z[:, 1] * x, x * x, torch.exp(x) * z[:, 1]):
        iv = out.to_interval()
        assert not bool((torch.isfinite(iv.lo) & torch.isfinite(iv.hi)).any())
