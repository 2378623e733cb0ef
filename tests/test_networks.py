import torch

from drlyap.networks import Controller, Lyapunov, saturate


def test_pinned_at_equilibrium_and_positive_definite():
    torch.manual_seed(0)
    v = Lyapunov(2, (16, 16), 4, alpha_hat=0.5, input_scale=(3.0, 8.0)).double()
    c = Controller(2, ((-2.0,), (3.0,)), (0.5,), (16,), init_gain=10.0).double()
    zero = torch.zeros(1, 2, dtype=torch.float64)
    assert v(zero).item() == 0.0
    assert torch.allclose(c(zero), torch.tensor([[0.5]], dtype=torch.float64))
    z = torch.randn(500, 2, dtype=torch.float64) * 3
    assert (v(z) > 0).all()
    u = c(z)
    assert (u >= -2.0).all() and (u <= 3.0).all()


def test_manual_input_gradient_matches_autograd():
    torch.manual_seed(1)
    v = Lyapunov(3, (8, 8), 5, alpha_hat=0.2, input_scale=(1.0, 2.0, 0.5)).double()
    z = torch.randn(40, 3, dtype=torch.float64, requires_grad=True)
    value, grad = v.value_and_grad(z)
    (auto,) = torch.autograd.grad(v(z).sum(), z)
    assert torch.allclose(value, v(z))
    assert torch.allclose(grad, auto, atol=1e-12)


def test_saturation_is_a_clamp_with_straight_through_gradient():
    x = torch.tensor([[-5.0], [0.3], [5.0]], requires_grad=True)
    low, high = torch.tensor([-1.0]), torch.tensor([2.0])
    y = saturate(x, low, high)
    assert torch.equal(y.detach(), torch.tensor([[-1.0], [0.3], [2.0]]))
    y.sum().backward()
    assert torch.equal(x.grad, torch.ones(3, 1))


def test_a_controller_with_a_linear_path_starts_at_its_gain_and_learns_a_correction():
    torch.manual_seed(2)
    c = Controller(3, ((0.0, 0.0), (6.0, 6.0)), (2.4, 2.4), (16,), input_scale=(1.0, 2.0, 0.5), skip=True).double()
    k = torch.randn(2, 3, dtype=torch.float64)
    assert c.set_linear(k)
    z = torch.randn(64, 3, dtype=torch.float64) * 0.3
    assert torch.allclose(c.raw(z), -z @ k.T, atol=1e-12)  # the correction starts at 0
    c(z).sum().backward()
    assert float(c.varphi.layers[-1].weight.grad.abs().max()) > 0  # and learns from there
    without = Controller(3, ((0.0, 0.0), (6.0, 6.0)), (2.4, 2.4), (16,))
    assert not without.set_linear(k)  # hidden layers and no linear path: only regression can fit it


def test_a_lyapunov_function_with_a_linear_path_starts_at_its_quadratic_and_learns_a_term():
    from drlyap.enclosures import Affine

    torch.manual_seed(5)
    scale = (1.0, 2.0, 0.5)
    v = Lyapunov(3, (8,), 3, 0.5, scale, skip=True).double()
    s = torch.tensor(scale, dtype=torch.float64)
    p = torch.diag(1.0 / s.square()) * 3.0 + 0.1
    assert v.set_quadratic(p)
    z = torch.randn(64, 3, dtype=torch.float64) * 0.3
    assert torch.allclose(v(z), ((z @ p) * z).sum(-1), atol=1e-12)  # the network's term starts at 0
    v(z).sum().backward()
    assert float(v.phi.layers[-1].weight.grad.abs().max()) > 0  # and learns from there
    with torch.no_grad():
        v.phi.layers[-1].weight.normal_()
    zg = z.clone().requires_grad_(True)
    value, grad = v.value_and_grad(zg)
    (auto,) = torch.autograd.grad(v(zg).sum(), zg)
    assert torch.allclose(value, v(z)) and torch.allclose(grad, auto, atol=1e-12)
    lo = torch.randn(20, 3, dtype=torch.float64)
    hi = lo + torch.rand(20, 3, dtype=torch.float64) * 0.5
    box_v, box_g = (e.to_interval() for e in v.value_and_grad(Affine.box(lo, hi)))
    pts = (lo[:, None] + (hi - lo)[:, None] * torch.rand(20, 300, 3, dtype=torch.float64)).reshape(-1, 3)
    with torch.no_grad():
        vals, grads = v.value_and_grad(pts)
    vals, grads = vals.reshape(20, 300), grads.reshape(20, 300, 3)
    assert bool((vals >= box_v.lo[:, None]).all() and (vals <= box_v.hi[:, None]).all())
    assert bool((grads >= box_g.lo[:, None]).all() and (grads <= box_g.hi[:, None]).all())
    assert not Lyapunov(3, (8,), 3, 0.5, scale).set_quadratic(p)  # hidden layers and no linear path: regression


def test_the_linear_paths_input_gradient_and_enclosure():
    from drlyap.enclosures import Affine
    from drlyap.networks import TanhMLP

    torch.manual_seed(3)
    mlp = TanhMLP([3, 8, 2], (1.0, 2.0, 0.5), skip=True).double()
    z = torch.randn(40, 3, dtype=torch.float64, requires_grad=True)
    out, hidden = mlp.forward_with_hidden(z)
    v = torch.randn(40, 2, dtype=torch.float64)
    (auto,) = torch.autograd.grad((mlp(z) * v).sum(), z)
    assert torch.allclose(mlp.vjp(hidden, v), auto, atol=1e-12)
    lo = torch.randn(20, 3, dtype=torch.float64)
    hi = lo + torch.rand(20, 3, dtype=torch.float64) * 0.5
    box = mlp(Affine.box(lo, hi)).to_interval()
    with torch.no_grad():
        pts = lo[:, None] + (hi - lo)[:, None] * torch.rand(20, 500, 3, dtype=torch.float64)
        vals = mlp(pts.reshape(-1, 3)).reshape(20, 500, 2)
    assert bool((vals >= box.lo[:, None]).all() and (vals <= box.hi[:, None]).all())
