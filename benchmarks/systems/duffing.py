"""A Duffing oscillator with an uncertain cubic stiffness: q'' = -q - k q^3 - 0.2 q' + f."""
import torch

from drlyap import UncertainSystem


def dynamics(x, u, p):
    (k,) = p.unbind(-1)
    q, v = x[:, 0], x[:, 1]
    return torch.stack([v, -q - k * q**3 - 0.2 * v + u[:, 0]], -1)


def make():
    return UncertainSystem(
        name="duffing", state_names=("q", "v"), input_names=("f",), param_names=("k",), nominal_params=(1.0,),
        uncertain=("k",), dynamics=dynamics, state_box=((-2, -2), (2, 2)), input_box=((-3,), (3,)),
        equilibrium=(0.0, 0.0), xi_sampler=lambda n, g: 0.2 * torch.randn(n, 1, generator=g, dtype=torch.float64),
        test_xi=(-0.5,),
    )
