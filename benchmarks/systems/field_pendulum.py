"""The field's pendulum (m = 0.15 kg, l = 0.5 m, b = 0.1, |u| <= 6, box [-12, 12]^2, theta = 0 upright) with an
uncertain damping b: theta'' = (g / l) sin(theta) - b theta' / (m l^2) + u / (m l^2)."""
import torch

from drlyap import UncertainSystem


def dynamics(x, u, p):
    m, l, b, g = p.unbind(-1)
    theta, omega = x[:, 0], x[:, 1]
    inertia = m * l * l
    return torch.stack([omega, g / l * torch.sin(theta) - b * omega / inertia + u[:, 0] / inertia], -1)


def make():
    return UncertainSystem(
        name="field-pendulum", state_names=("theta", "omega"), input_names=("u",),
        param_names=("m", "l", "b", "g"), nominal_params=(0.15, 0.5, 0.1, 9.81), uncertain=("b",),
        dynamics=dynamics, state_box=((-12, -12), (12, 12)), input_box=((-6,), (6,)), equilibrium=(0.0, 0.0),
        xi_sampler=lambda n, g: 0.02 * torch.randn(n, 1, generator=g, dtype=torch.float64), test_xi=(-0.05,),
    )
