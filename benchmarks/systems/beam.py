"""A pendulum on a cart-like arm whose input acts through cos(q), with an uncertain damping b:
q'' = sin(q) - b q' + cos(q) f (upright at q = 0, the input's authority falling off away from it)."""
import torch

from drlyap import UncertainSystem


def dynamics(x, u, p):
    (b,) = p.unbind(-1)
    q, v = x[:, 0], x[:, 1]
    return torch.stack([v, torch.sin(q) - b * v + torch.cos(q) * u[:, 0]], -1)


def make():
    return UncertainSystem(
        name="beam", state_names=("q", "v"), input_names=("f",), param_names=("b",), nominal_params=(0.3,),
        uncertain=("b",), dynamics=dynamics, state_box=((-1.2, -2), (1.2, 2)), input_box=((-2.5,), (2.5,)),
        equilibrium=(0.0, 0.0), xi_sampler=lambda n, g: 0.05 * torch.randn(n, 1, generator=g, dtype=torch.float64),
        test_xi=(-0.15,),
    )
