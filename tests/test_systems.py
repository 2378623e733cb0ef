import math

import pytest
import torch

from drlyap.systems import UncertainSystem, get_system, mountain_car, pendulum, system_names


def test_pendulum_design_model_matches_paper_w1_w2():
    """The autodiff W equals the paper's printed first-order expansion (eq. uncertain_pendulum_dynamics)."""
    sys_ = pendulum()
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(50, 2, generator=gen, dtype=torch.float64) * 6 - 3
    u = torch.rand(50, 1, generator=gen, dtype=torch.float64) * 30 - 15
    f, w = sys_.design_model(x, u)
    m, l, b, g = 1.0, 1.0, 0.13, 9.81
    theta, omega = x[:, 0], x[:, 1]
    w1 = torch.stack([torch.zeros_like(omega), (b * omega - u[:, 0]) / (m**2 * l**2)], -1)
    w2 = torch.stack([torch.zeros_like(omega), -omega / (m * l**2)], -1)
    assert torch.allclose(w[:, :, 0], w1, atol=1e-12)
    assert torch.allclose(w[:, :, 1], w2, atol=1e-12)
    expected_f = torch.stack([omega, (m * g * l * torch.sin(theta) - b * omega + u[:, 0]) / (m * l**2)], -1)
    assert torch.allclose(f, expected_f, atol=1e-12)


def test_weighted_design_equals_full_w():
    sys_ = pendulum()
    x = torch.randn(20, 2, dtype=torch.float64)
    u = torch.randn(20, 1, dtype=torch.float64)
    gv = torch.randn(20, 2, dtype=torch.float64)
    f, w = sys_.design_model(x, u)
    gf, gw = sys_.weighted_design(x, u, gv)
    assert torch.allclose(gf, (gv * f).sum(-1))
    assert torch.allclose(gw, torch.einsum("bn,bnk->bk", gv, w))


def test_mountain_car_w_is_input_and_model_affine_in_power():
    sys_ = mountain_car()
    x = torch.randn(10, 2, dtype=torch.float64)
    u = torch.randn(10, 1, dtype=torch.float64)
    f, w = sys_.design_model(x, u)
    assert torch.allclose(w[:, 1, 0], u[:, 0]) and torch.all(w[:, 0, 0] == 0)
    xi = torch.tensor([-0.0003], dtype=torch.float64)
    # affine in power: design model is exact
    assert torch.allclose(sys_.true_dynamics(x, u, xi), f + (w @ xi[:, None])[..., 0], atol=1e-15)


def test_true_model_differs_from_design_model_for_pendulum():
    sys_ = pendulum()
    x = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    u = torch.tensor([[5.0]], dtype=torch.float64)
    xi = torch.tensor([0.1, 0.05], dtype=torch.float64)
    f, w = sys_.design_model(x, u)
    design = f + (w @ xi[:, None])[..., 0]
    true = sys_.true_dynamics(x, u, xi)
    m = 1.1
    expected = (m * 9.81 * math.sin(1.0) - 0.18 * 2.0 + 5.0) / m
    assert true[0, 1].item() == pytest.approx(expected, rel=1e-12)
    assert abs(true[0, 1] - design[0, 1]) > 1e-3


def test_local_coordinates_wrap_angles_and_shift_equilibrium():
    p = pendulum()
    x = torch.tensor([[3 * math.pi / 2, 1.0], [-math.pi / 2, 1.0]], dtype=torch.float64)
    z = p.to_local(x)
    assert torch.allclose(z[0], z[1]) and z[0, 0].item() == pytest.approx(-math.pi / 2)
    mc = mountain_car()
    assert torch.allclose(mc.to_local(torch.tensor([[math.pi / 6, 0.0]])), torch.zeros(1, 2), atol=1e-7)


def test_registry_and_unknown_system():
    assert {"pendulum", "mountain-car"} <= set(system_names())
    with pytest.raises(ValueError, match="unknown system 'nope'.*valid"):
        get_system("nope")


def _user_system(**over):
    def dyn(x, u, p):
        (a,) = p.unbind(-1)
        return torch.stack([x[:, 1], a * x[:, 0] + u[:, 0]], -1)

    spec = dict(name="double-int", state_names=("q", "v"), input_names=("f",), param_names=("a",), nominal_params=(0.5,),
                uncertain=("a",), dynamics=dyn, state_box=((-1, -1), (1, 1)), input_box=((-2,), (2,)),
                equilibrium=(0.0, 0.0))
    spec.update(over)
    return UncertainSystem(**spec)


def test_user_system_in_a_few_lines():
    s = _user_system()
    x = torch.tensor([[0.3, 0.1]], dtype=torch.float64)
    f, w = s.design_model(x, torch.zeros(1, 1, dtype=torch.float64))
    assert torch.allclose(w[0, :, 0], torch.tensor([0.0, 0.3], dtype=torch.float64))


@pytest.mark.parametrize("over, message", [
    (dict(state_box=((-1, 1), (1, -1))), "empty or inverted"),
    (dict(state_box=((-1, -1), (1, float("nan")))), "non-finite"),
    (dict(input_box=((2,), (2,))), "empty or inverted"),
    (dict(uncertain=("b",)), "subset"),
    (dict(equilibrium=(0.0,)), "equilibrium has 1"),
    (dict(equilibrium=(0.5, 0.5)), "is not zero"),
    (dict(angle_dims=(5,)), "angle_dims"),
])
def test_bad_system_definitions_are_named(over, message):
    with pytest.raises(ValueError, match=message):
        _user_system(**over)


def test_check_xi_validates_count_and_finiteness():
    p = pendulum()
    assert p.check_xi([0.1, 0.05]).shape == (2,)
    with pytest.raises(ValueError, match="takes 2 xi value"):
        p.check_xi([0.1])
    with pytest.raises(ValueError, match="finite"):
        p.check_xi([0.1, float("nan")])
