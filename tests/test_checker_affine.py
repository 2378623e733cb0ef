"""The checker's second-order forms (drlyap.checker.affine): every bound holds at dense samples of its boxes (corners
included), the quadratic maximisation is never below a brute-force maximum, and the forms are tighter than
intervals on small boxes (what they are for)."""

import pytest
import torch

from drlyap.checker.affine import Af
from drlyap.checker.arith import Iv
from drlyap.checker.leaves import _by_forms
from drlyap.checker.model import Pair, Residual, affine_upper, form_upper, sublevel_form_upper
from drlyap.checker.quadratic import _dual_max, _quick_span, _quick_spans, quad_max, quad_max_minus, quad_span
from drlyap.conditions import DRPointwise
from drlyap.runs.certificates import condition_claim
from handmade import linear_pair, small_pendulum

F64 = torch.float64


def boxes(count: int, k: int, width: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    lo = (torch.rand(count, k, generator=g, dtype=F64) * 2 - 1) * 2
    return lo, lo + torch.rand(count, k, generator=g, dtype=F64) * width


def points(lo: torch.Tensor, hi: torch.Tensor, count: int = 3000, seed: int = 1) -> torch.Tensor:
    """``(count + 2^k, B, k)``: uniform samples and every corner of each box."""
    k = lo.shape[-1]
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(count, *lo.shape, generator=g, dtype=F64)
    corners = torch.cartesian_prod(*[torch.tensor([0.0, 1.0], dtype=F64)] * k).reshape(-1, 1, k)
    return lo + (hi - lo) * torch.cat([t, corners.expand(-1, *lo.shape)])


G = torch.Generator().manual_seed(5)
W1, B1, W2 = (torch.randn(6, 3, generator=G, dtype=F64), torch.randn(6, generator=G, dtype=F64),
              torch.randn(2, 6, generator=G, dtype=F64))
LOW, HIGH = torch.tensor(-0.5, dtype=F64), torch.tensor(1.0, dtype=F64)


def expression(x):
    """A network, the dynamics' functions, products, a quotient, a clamp, abs and a norm: ``(B, 3) -> (B, 7)``."""
    h = x.linear(W1, B1).tanh()
    y = h.linear(W2)
    a = torch.sin(y[:, 0:1]) * torch.cos(x[:, 1:2]) + y[:, 1:2].square() - x[:, 0:1] / (2.5 + torch.cos(x[:, 2:3]))
    a = a + torch.exp(x[:, 0:1] * 0.3) - (x.square().sum(-1) + 0.1).unsqueeze(-1).sqrt()
    c = a.clamp(LOW, HIGH)
    return torch.cat([a, c, x.norm().unsqueeze(-1), 1.0 - a, (a * c).abs(), y[..., 1:2] * 2.0, x[:, 0:1] ** 3], -1)


@pytest.mark.parametrize("width", [0.02, 0.3, 2.0])
def test_forms_enclose_dense_samples(width):
    lo, hi = boxes(300, 3, width, seed=int(width * 100))
    form = expression(Af.seed(lo, hi))
    pts = points(lo, hi)
    values = expression(Iv.point(pts.reshape(-1, 3)))
    values = values.lo.reshape(pts.shape[0], 300, -1)
    assert bool((values >= form.lo).all()), "a lower bound lies above a sampled value"
    assert bool((values <= form.hi).all()), "an upper bound lies below a sampled value"


def test_forms_are_tighter_than_intervals_on_small_boxes():
    lo, hi = boxes(300, 3, 0.05, seed=9)
    form, plain = expression(Af.seed(lo, hi)), expression(Iv(lo, hi))
    pts = points(lo, hi, count=2000)
    values = expression(Iv.point(pts.reshape(-1, 3))).lo.reshape(pts.shape[0], 300, -1)
    true = values.amax(0) - values.amin(0)
    column = 0  # the network through sin, cos, a quotient, exp and sqrt
    assert float(((form.hi - form.lo)[:, column] / true[:, column]).median()) < 1.1
    assert float(((plain.hi - plain.lo)[:, column] / true[:, column]).median()) > 2.0


@pytest.mark.parametrize("k", [1, 3, 4])
def test_quad_max_is_never_below_the_brute_force_maximum(k):
    g = torch.Generator().manual_seed(k)
    lin = torch.randn(500, k, generator=g, dtype=F64)
    q = torch.randn(500, k, k, generator=g, dtype=F64)
    grid = torch.linspace(-1, 1, 9 if k < 4 else 7, dtype=F64)
    e = torch.cartesian_prod(*[grid] * k).reshape(-1, k)  # (P, k), the corners among them
    values = (lin[:, None] * e).sum(-1) + torch.einsum("pi,bij,pj->bp", e, q, e)
    for dual in (False, True):
        assert bool((quad_max(lin, q, dual=dual) >= values.amax(-1)).all())
    quick = _quick_span(lin, q)  # the cheap bound used inside products
    assert bool((quick.hi >= values.amax(-1)).all()) and bool((quick.lo <= values.amin(-1)).all())
    span = quad_span(lin, q)  # both sides at once: the corner bound of the form and of its negation
    assert torch.allclose(span.hi, quad_max(lin, q), rtol=1e-12) and torch.allclose(-span.lo, quad_max(-lin, -q))
    alone = _quick_spans(lin, q, with_lin=False)[0]
    q_values = torch.einsum("pi,bij,pj->bp", e, q, e)
    assert bool((alone.hi >= q_values.amax(-1)).all()) and bool((alone.lo <= q_values.amin(-1)).all())
    convex = q @ q.transpose(-1, -2)  # positive semidefinite: the maximum is at a corner, found exactly
    corners = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64)] * k).reshape(-1, k)
    exact = ((lin[:, None] * corners).sum(-1) + torch.einsum("pi,bij,pj->bp", corners, convex, corners)).amax(-1)
    assert torch.allclose(quad_max(lin, convex), exact, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("k", [2, 4])
def test_the_s_procedure_bound_is_never_below_the_brute_force_maximum(k):
    """``quad_max_minus`` combines two forms' corner values per multiplier without forming the products: it must be
    the same bound as :func:`quad_max` of the combined form, never below the true maximum."""
    g = torch.Generator().manual_seed(10 + k)
    lin, q = torch.randn(60, 3, k, generator=g, dtype=F64), torch.randn(60, 3, k, k, generator=g, dtype=F64)
    lin2, q2 = torch.randn(60, k, generator=g, dtype=F64), torch.randn(60, k, k, generator=g, dtype=F64)
    lam = torch.tensor([0.0, 0.25, 1.0, 8.0], dtype=F64).expand(60, 3, 4)
    e = torch.cartesian_prod(*[torch.linspace(-1, 1, 9, dtype=F64)] * k).reshape(-1, k)
    combined_l = lin[:, :, None] - lam[..., None] * lin2[:, None, None]
    combined_q = q[:, :, None] - lam[..., None, None] * q2[:, None, None]
    brute = ((combined_l[..., None, :] * e).sum(-1) + torch.einsum("pi,bqlij,pj->bqlp", e, combined_q, e)).amax(-1)
    for dual in (False, True):
        bound = quad_max_minus(lin, q, lin2, q2, lam, dual)
        assert bool((bound >= brute).all())
        assert torch.allclose(bound, quad_max(combined_l, combined_q, dual), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("k", [2, 4, 6])
def test_a_concave_forms_maximum_on_a_face_of_the_cube_is_found(k):
    """A concave form whose unconstrained maximiser lies outside the cube (V's minimum over a box that straddles a
    sublevel set's boundary, negated): the corner and dual bounds are loose, the face bound is the maximum where its
    search finds it, and never below it for any form."""
    g = torch.Generator().manual_seed(30 + k)
    a = torch.randn(80, k, k, generator=g, dtype=F64)
    concave = -(a @ a.transpose(-1, -2))
    lin = 6 * torch.randn(80, k, generator=g, dtype=F64)
    x = torch.rand(80, 64, k, generator=g, dtype=F64) * 2 - 1  # the true maximum by projected gradient ascent
    step = 1 / (2 * torch.linalg.eigvalsh(-concave)[:, -1])
    for _ in range(3000):
        x = (x + step[:, None, None] * (lin[:, None] + 2 * x @ concave)).clamp(-1, 1)
    best = ((lin[:, None] * x).sum(-1) + torch.einsum("bsk,bkl,bsl->bs", x, concave, x)).amax(-1)
    bound = quad_max(lin, concave, dual=True)
    before = torch.minimum(quad_max(lin, concave), _dual_max(lin, concave))  # the corner and dual bounds alone
    assert bool((bound >= best).all())
    assert float(torch.isclose(bound, best, rtol=1e-8, atol=1e-8 * float(concave.abs().max())).double().mean()) >= 0.85
    assert float((bound - best).median()) < 0.01 * float((before - best).median())  # what the face bound is for
    q = torch.randn(80, k, k, generator=g, dtype=F64)  # any form: still above every sampled value
    e = torch.cat([torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=F64)] * k).reshape(-1, k),
                   torch.rand(20000, k, generator=g, dtype=F64) * 2 - 1])
    values = (lin[:, None] * e).sum(-1) + torch.einsum("pi,bij,pj->bp", e, q, e)
    assert bool((quad_max(lin, q, dual=True) >= values.amax(-1)).all())


def test_the_dual_bound_sees_curvature_along_mixed_directions():
    """``q`` curved downward along ``(1, 1, ..)`` with a linear part along it: the corner bound cannot see that the
    two cancel, the dual bound does; both stay above the brute-force maximum."""
    k = 4
    g = torch.Generator().manual_seed(7)
    ones = torch.ones(k, dtype=F64)
    q = -3.0 * torch.outer(ones, ones).expand(200, k, k) + 0.05 * torch.randn(200, k, k, generator=g, dtype=F64)
    lin = 2.0 * ones + 0.1 * torch.randn(200, k, generator=g, dtype=F64)
    e = torch.cartesian_prod(*[torch.linspace(-1, 1, 11, dtype=F64)] * k).reshape(-1, k)
    brute = ((lin[:, None] * e).sum(-1) + torch.einsum("pi,bij,pj->bp", e, q, e)).amax(-1)
    corner, dual = quad_max(lin, q), quad_max(lin, q, dual=True)
    assert bool((dual >= brute).all()) and bool((dual <= corner).all())
    assert float((dual - brute).median()) < 0.5 * float((corner - brute).median())


def test_a_norm_whose_argument_reaches_zero_is_enclosed():
    lo, hi = boxes(400, 3, 1.0, seed=3)
    lo[:100], hi[:100] = -hi[:100].abs(), hi[:100].abs()  # boxes around the origin
    form = Af.seed(lo, hi).norm()
    pts = points(lo, hi)
    values = pts.norm(dim=-1)
    assert bool((values >= form.lo).all()) and bool((values <= form.hi).all())
    sqrt = Af.seed(lo - 0.5, hi)[:, 0].sqrt()  # outside the domain somewhere: the whole line there
    assert bool(torch.isinf(sqrt.hi[(lo[:, 0] - 0.5) < 0]).all())


def pendulum_residual(radius: float, risk_level: float) -> Residual:
    """The checker's DR pointwise residual of the hand-made pendulum pair, three samples of xi, decay 0.05."""
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    weights = {"lyapunov": lyap.state_dict(), "controller": ctrl.state_dict()}
    xi = torch.tensor([[0.02, 0.01], [-0.03, 0.0], [0.05, -0.02]], dtype=F64)
    return Residual(condition_claim(DRPointwise(radius, risk_level, xi, decay_rate=0.05)),
                    Pair(weights, lyap.alpha_hat, 2), system)


def test_the_residual_and_its_sublevel_bound_hold_at_samples():
    """On the hand-made pendulum pair: the residual's second-order bound over boxes is above the residual at every
    sample, and the S-procedure's bound above it at every sample where V <= level."""
    residual = pendulum_residual(0.01, 0.3)
    lo, hi = boxes(200, 2, 0.4, seed=11)
    pts = points(lo, hi, count=1500)
    comps, value = residual.terms(Iv.point(pts.reshape(-1, 2)))
    actual = residual.combine_upper(comps.hi).reshape(pts.shape[0], 200)
    assert bool((actual <= affine_upper(residual, lo, hi)).all())
    v = value.hi.reshape(pts.shape[0], 200)
    level = float(v.median())
    bound = affine_upper(residual, lo, hi, level)
    where = v <= level
    assert bool((torch.where(where, actual, -torch.inf) <= bound).all())
    forms, values = residual.terms(Af.seed(lo, hi))
    per_component = sublevel_form_upper(forms, values, level)  # (B, Q)
    sampled = comps.hi.reshape(pts.shape[0], 200, -1)
    assert bool((torch.where(where[..., None], sampled, -torch.inf) <= per_component).all())


@pytest.mark.parametrize("width", [0.01, 0.5, 3.0])
def test_tanh_of_a_curved_form_encloses_dense_samples(width):
    """tanh of a form with a quadratic part, over ranges near 0 (where its third derivative is largest), on its
    flanks (where the third derivative changes sign) and in saturation: the narrower of the two forms holds."""
    g = torch.Generator().manual_seed(int(width * 100) + 3)
    lo = torch.rand(400, 2, generator=g, dtype=F64) * 6 - 3
    hi = lo + torch.rand(400, 2, generator=g, dtype=F64) * width

    def f(x):
        return (x[:, 0:1] * 1.7 - x[:, 1:2] * 0.4 + x[:, 0:1] * x[:, 1:2] * 0.3).tanh()

    form = f(Af.seed(lo, hi))
    pts = points(lo, hi, count=4000)
    values = torch.tanh(pts[..., 0:1] * 1.7 - pts[..., 1:2] * 0.4 + pts[..., 0:1] * pts[..., 1:2] * 0.3)
    assert bool((values >= form.lo).all()) and bool((values <= form.hi).all())


def test_the_flat_norm_bounds_the_residual_at_samples_and_helps_where_the_norm_nears_zero():
    """The DR norm as the constant form of its interval norm (``terms(flat_norm=True)``): its bound of the residual
    holds at every sample (with a level, where V <= level), and ``_by_forms`` proves a box when either the norm's own
    form or the flat one does."""
    residual = pendulum_residual(0.05, 0.1)
    assert residual.has_norm
    lo, hi = boxes(300, 2, 0.4, seed=12)
    pts = points(lo, hi, count=1500)
    comps, value = residual.terms(Iv.point(pts.reshape(-1, 2)))
    sampled = comps.hi.reshape(pts.shape[0], 300, -1)
    v = value.hi.reshape(pts.shape[0], 300)
    level = float(v.median())
    for flat in (False, True):
        forms, values = residual.terms(Af.seed(lo, hi), flat_norm=flat)
        assert bool((sampled <= forms.hi).all())  # every component's bound, each sample of xi
        per_component = sublevel_form_upper(forms, values, level)
        assert bool((torch.where((v <= level)[..., None], sampled, -torch.inf) <= per_component).all())
    plain = residual.terms(Af.seed(lo, hi))
    flat = residual.terms(Af.seed(lo, hi), flat_norm=True)
    by_form = (form_upper(residual, *plain, level) <= 0) | (plain[1].interval(dual=True).lo > level)
    by_flat = form_upper(residual, *flat, level) <= 0
    assert torch.equal(_by_forms(residual, lo, hi, level), by_form | by_flat)


def test_a_products_one_signed_higher_part_is_centred_first():
    """``x = L^2`` (a one-signed quadratic part over [0, a], no linear part) times a linear ``y``: written about the
    middle of that range, the product's remainder is about ``a dev(y)`` wide instead of ``2 a dev(y)``."""
    lo, hi = boxes(30, 2, 0.2, seed=3)
    centre = (lo + hi) / 2
    lo, hi = lo - centre, hi - centre
    z = Af.seed(lo, hi)
    x, y = (z[:, 0] - z[:, 1]).square(), z[:, 0] + z[:, 1] * 2.0
    a = x.interval().hi - x.interval().lo
    out = x * y
    pts = points(lo, hi)
    values = ((pts[..., 0] - pts[..., 1]) ** 2 * (pts[..., 0] + 2 * pts[..., 1]))
    assert bool((values >= out.lo).all() and (values <= out.hi).all())
    assert bool(((out.r.hi - out.r.lo) <= 1.05 * a * y._lmag()).all())
