"""A Van der Pol oscillator with an uncertain damping mu: q'' = mu (1 - q^2) q' - q + f."""
import torch

from drlyap import UncertainSystem


def dynamics(x, u, p):
    (mu,) = p.unbind(-1)
    q, v = x[:, 0], x[:, 1]
    return torch.stack([v, mu * (1 - q * q) * v - q + u[:, 0]], -1)


def make():
    return UncertainSystem(
        name="vanderpol", state_names=("q", "v"), input_names=("f",), param_names=("mu",), nominal_params=(1.0,),
        uncertain=("mu",), dynamics=dynamics, state_box=((-1.5, -1.5), (1.5, 1.5)), input_box=((-2,), (2,)),
        equilibrium=(0.0, 0.0), xi_sampler=lambda n, g: 0.1 * torch.randn(n, 1, generator=g, dtype=torch.float64),
        test_xi=(0.3,),
    )
