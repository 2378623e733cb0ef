"""The built-in systems: the paper's inverted pendulum and mountain car, a cart-pole and a planar quadrotor.

Each is a factory returning an :class:`~drlyap.systems.model.UncertainSystem` with its true parametric dynamics,
its training distribution of xi and the paper's (or a chosen) test shift; its training recipe (the defaults its
training and proofs take) is in :mod:`drlyap.recipes`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from drlyap import recipes
from drlyap.systems.model import UncertainSystem


def _pendulum(x: Tensor, u: Tensor, p: Tensor) -> Tensor:
    theta, omega = x.unbind(-1)
    m, l, b, g = p.unbind(-1)
    return torch.stack([omega, (m * g * l * torch.sin(theta) - b * omega + u[:, 0]) / (m * l * l)], dim=-1)


def _pendulum_xi(count: int, gen: torch.Generator) -> Tensor:
    mass = torch.rand(count, generator=gen, dtype=torch.float64) * 0.12 - 0.04  # U(-0.04, 0.08)
    damping = torch.randn(count, generator=gen, dtype=torch.float64) * 0.02  # N(0, 0.02)
    return torch.stack([mass, damping], dim=-1)


def _mountain_car(x: Tensor, u: Tensor, p: Tensor) -> Tensor:
    pos, vel = x.unbind(-1)
    power, slope = p.unbind(-1)
    return torch.stack([vel, -slope * torch.cos(3 * pos) + power * u[:, 0]], dim=-1)


def _mountain_car_xi(count: int, gen: torch.Generator) -> Tensor:
    return (torch.randn(count, generator=gen, dtype=torch.float64) * 0.0002).reshape(count, 1)  # N(0, 0.0002)


def _cartpole(x: Tensor, u: Tensor, p: Tensor) -> Tensor:
    _, theta, velocity, omega = x.unbind(-1)
    m_c, m_p, l, g, b = p.unbind(-1)
    s, c = torch.sin(theta), torch.cos(theta)
    torque = -b * omega  # viscous damping torque at the pivot (acts on the pole, reacts on the cart)
    den = m_c + m_p * torch.square(s)
    spin = l * torch.square(omega)
    x_acc = (u[:, 0] + m_p * s * (spin - g * c) - torque * c / l) / den
    th_acc = (-u[:, 0] * c - m_p * spin * c * s + (m_c + m_p) * g * s + (m_c + m_p) * torque / (m_p * l)) / (l * den)
    return torch.stack([velocity, omega, x_acc, th_acc], dim=-1)


def _cartpole_xi(count: int, gen: torch.Generator) -> Tensor:
    pole_mass = torch.rand(count, generator=gen, dtype=torch.float64) * 0.04 - 0.01  # U(-0.01, 0.03) kg
    damping = torch.rand(count, generator=gen, dtype=torch.float64) * 0.02  # U(0, 0.02) N m s/rad
    return torch.stack([pole_mass, damping], dim=-1)


# The planar quadrotor's uncertain parameters are declared in units that make their shifts comparable
# (the Wasserstein ball of the DR conditions is Euclidean in xi): inertia in g m^2 (1e-3 kg m^2), arm
# length in cm. The angular acceleration arm (u1 - u2) / inertia then carries the factor
# cm / (g m^2) = 1e-2 m / (1e-3 kg m^2) = 10 / (kg m).
_QUAD_UNIT = 10.0


def _quadrotor2d(x: Tensor, u: Tensor, p: Tensor) -> Tensor:
    _, _, theta, vx, vy, omega = x.unbind(-1)
    m, inertia, arm, g = p.unbind(-1)
    u1, u2 = u[:, 0], u[:, 1]
    thrust = u1 + u2
    return torch.stack([vx, vy, omega, -torch.sin(theta) * thrust / m, torch.cos(theta) * thrust / m - g,
                        _QUAD_UNIT * arm * (u1 - u2) / inertia], dim=-1)


def _quadrotor2d_xi(count: int, gen: torch.Generator) -> Tensor:
    inertia = torch.rand(count, generator=gen, dtype=torch.float64) * 0.8 - 0.2  # U(-0.2, 0.6) g m^2
    arm = torch.randn(count, generator=gen, dtype=torch.float64) * 0.5  # N(0, 0.5) cm
    return torch.stack([inertia, arm], dim=-1)


def pendulum(u_max: float = 15.0) -> UncertainSystem:
    """The paper's inverted pendulum (theta = 0 upright), uncertain mass and damping, ``|u| <= u_max``."""
    return UncertainSystem(
        name="pendulum" if u_max == 15.0 else f"pendulum-u{u_max:g}",
        state_names=("theta", "theta_dot"), input_names=("torque",),
        param_names=("mass", "length", "damping", "gravity"), nominal_params=(1.0, 1.0, 0.13, 9.81),
        uncertain=("mass", "damping"), dynamics=_pendulum,
        state_box=((-math.pi, -8.0), (math.pi, 8.0)), input_box=((-u_max,), (u_max,)),
        equilibrium=(0.0, 0.0), angle_dims=(0,), test_box=((-math.pi, -6.0), (math.pi, 6.0)),
        xi_sampler=_pendulum_xi, test_xi=(0.1, 0.05), reference_states=((math.pi, 0.0), (-math.pi / 2, 5.5)),
        rl_timing=(0.05, 10.0), rl_reward_weights=((1.0, 0.1), (0.001,)),  # the paper's RL cost, 200-step episodes
        defaults=recipes.PENDULUM,
        sim_dt=0.01, horizon=20.0, state_units=("rad", "rad/s"), input_units=("N m",), time_unit="s",
        description="Inverted pendulum (paper Sec. VII-A): m=1, l=1, b=0.13, g=9.81; xi = (mass, damping) shift.",
    )


def mountain_car() -> UncertainSystem:
    """The paper's continuous mountain car, equilibrium at the hill top (pi/6, 0), uncertain power."""
    return UncertainSystem(
        name="mountain-car", state_names=("position", "velocity"), input_names=("force",),
        param_names=("power", "slope"), nominal_params=(0.0015, 0.0025), uncertain=("power",),
        dynamics=_mountain_car, state_box=((-2.0, -0.4), (2.0, 0.4)), input_box=((-2.0,), (2.0,)),
        equilibrium=(math.pi / 6, 0.0), test_box=((-1.0, -0.1), (1.0, 0.1)),
        xi_sampler=_mountain_car_xi, test_xi=(-0.0003,), reference_states=((-math.pi / 6, 0.0),),
        rl_timing=(1.0, 500.0),  # the gym mountain car's step
        defaults=recipes.MOUNTAIN_CAR,
        sim_dt=0.5, horizon=1500.0, state_units=("u.", "u./step"), input_units=("u.",), time_unit="step",
        description=("Mountain car (paper Sec. VII-B): p=0.0015, |u|<=2, goal (pi/6, 0); xi = power shift. "
                     "Units are those of the model (u.), time in steps of the gym environment (1 step = 1 time unit)."),
    )


def cartpole() -> UncertainSystem:
    """Cart-pole balancing the pole upright, uncertain pole mass and pivot damping, ``|u| <= 30 N``.

    States ``(x, theta, xdot, thetadot)`` in m, rad, m/s, rad/s with ``theta = 0`` upright (positive
    ``theta`` tilts the pole towards +x); input: horizontal force ``u`` on the cart in N. Model: cart of
    mass ``m_c`` on a frictionless track, point mass ``m_p`` at the tip of a massless pole of length
    ``l`` (R. Tedrake, *Underactuated Robotics*, ch. "Acrobots, Cart-Poles, and Quadrotors", with theta
    measured from the upright instead of the hanging position), plus a viscous pivot damping torque
    ``tau = -b thetadot`` on the pole (and its reaction on the cart). Lagrange's equations with the
    generalised forces ``(u, tau)`` give, with ``D = m_c + m_p sin^2 th``::

        xddot  = (u + m_p sin th (l thd^2 - g cos th) - tau cos th / l) / D
        thddot = (-u cos th - m_p l thd^2 cos th sin th + (m_c + m_p) g sin th
                  + (m_c + m_p) tau / (m_p l)) / (l D)

    (``b = 0``: Tedrake's equations). Nominal ``m_c = 1 kg``, ``m_p = 0.1 kg``, ``l = 1 m``,
    ``g = 9.81 m/s^2``, ``b = 0`` (frictionless pivot); ``x* = 0``, ``u* = 0``.

    Uncertainty ``xi = (pole_mass [kg], damping [N m s/rad])`` shifts ``m_p`` and ``b``. The pole mass
    enters the dynamics *nonlinearly* (through ``D`` and ``tau / m_p``), so ``f + W xi`` with
    ``W = dF/dp`` at the nominal (the autodiff linearisation in xi, as for the pendulum's mass) is exact
    only to first order; the damping enters affinely. Simulations and evaluations use the true model
    with the exact perturbed parameters. Training distribution: ``pole_mass ~ U(-0.01, 0.03)``
    (-10%..+30%), ``damping ~ U(0, 0.02)``; out-of-distribution test shift ``(0.04, 0.04)`` (a 40%
    heavier pole and a damped pivot). State box ``[-2, 2] x [-1, 1] x [-3, 3] x [-3, 3]``, test box
    ``[-0.5, 0.5] x [-0.25, 0.25] x [-0.5, 0.5] x [-0.5, 0.5]``.
    """
    return UncertainSystem(
        name="cartpole", state_names=("x", "theta", "x_dot", "theta_dot"), input_names=("force",),
        param_names=("cart_mass", "pole_mass", "length", "gravity", "damping"),
        nominal_params=(1.0, 0.1, 1.0, 9.81, 0.0), uncertain=("pole_mass", "damping"), dynamics=_cartpole,
        # X is wider than the pole's [-1, 1] in the cart's coordinates: catching the pole moves the cart (from the
        # test box an LQR reaches 1.4 m and 2.3 m/s), and a certified invariant set must hold those trajectories
        state_box=((-2.0, -1.0, -3.0, -3.0), (2.0, 1.0, 3.0, 3.0)), input_box=((-30.0,), (30.0,)),
        equilibrium=(0.0, 0.0, 0.0, 0.0), angle_dims=(1,),
        test_box=((-0.5, -0.25, -0.5, -0.5), (0.5, 0.25, 0.5, 0.5)),
        xi_sampler=_cartpole_xi, test_xi=(0.04, 0.04),
        reference_states=((0.5, 0.25, 0.0, 0.0), (-0.5, -0.25, 0.5, 0.5)),
        rl_timing=(0.02, 10.0),
        defaults=recipes.CARTPOLE,
        sim_dt=0.01, horizon=10.0, state_units=("m", "rad", "m/s", "rad/s"), input_units=("N",), time_unit="s",
        plot_dims=(1, 3),  # (theta, theta_dot): the pole's phase plane
        description=("Cart-pole (Tedrake, Underactuated Robotics), theta=0 upright: m_c=1, m_p=0.1, l=1, g=9.81, "
                     "|u|<=30 N, pivot damping b=0 nominal; xi = (pole mass [kg], damping [N m s/rad]) shift."),
    )


def quadrotor2d() -> UncertainSystem:
    """Planar quadrotor hovering at the origin, uncertain inertia and arm length, thrusts in ``[0, 5.96] N``.

    States ``(x, y, theta, xdot, ydot, thetadot)`` in m, m, rad, m/s, m/s, rad/s (``y`` up, ``theta`` the
    roll angle); inputs: the two rotor thrusts ``u1, u2`` in N. Model as in the neural Lyapunov control
    literature (Dai et al., "Lyapunov-stable neural-network control", RSS 2021; Yang et al., "Lyapunov-stable
    neural control for state and output feedback", ICML 2024)::

        xddot  = -sin th (u1 + u2) / m
        yddot  =  cos th (u1 + u2) / m - g
        thddot =  l (u1 - u2) / I

    Nominal ``m = 0.486 kg``, ``I = 0.00383 kg m^2``, ``l = 0.25 m``, ``g = 9.81 m/s^2``; inputs in
    ``[0, 1.25 m g] = [0, 5.96] N`` each (2.5x the hover thrust; the box is not symmetric about ``u*``).
    Equilibrium ``x* = 0`` with the hover input ``u1* = u2* = m g / 2``.

    Uncertainty ``xi = (inertia_gm2, arm_cm)`` shifts ``I`` and ``l``, declared in g m^2 (``I = 3.83``)
    and cm (``l = 25``) so that both shifts are of the same order (the Wasserstein ball is Euclidean in
    xi); hence ``thddot = 10 l[cm] (u1 - u2) / I[g m^2]``. Both leave hover an equilibrium (they only
    scale the torque, which is zero at hover); an uncertain mass would move the hover input (not modelled).
    The inertia enters nonlinearly (``1 / I``): ``W`` is its first-order linearisation at the nominal,
    the simulations use the exact perturbed parameters. Training distribution: ``inertia ~ U(-0.2, 0.6)``
    g m^2 (-5%..+16%), ``arm ~ N(0, 0.5)`` cm (2%); out-of-distribution test shift ``(0.8, -2.5)`` (+21%
    inertia, -10% arm: about 0.74x the nominal torque authority). State box
    ``[-0.75, 0.75]^2 x [-pi/2, pi/2] x [-4, 4]^2 x [-3, 3]``.
    """
    mass, gravity = 0.486, 9.81
    hover = mass * gravity / 2
    return UncertainSystem(
        name="quadrotor2d", state_names=("x", "y", "theta", "x_dot", "y_dot", "theta_dot"),
        input_names=("thrust_1", "thrust_2"),
        param_names=("mass", "inertia_gm2", "arm_cm", "gravity"), nominal_params=(mass, 3.83, 25.0, gravity),
        uncertain=("inertia_gm2", "arm_cm"), dynamics=_quadrotor2d,
        state_box=((-0.75, -0.75, -math.pi / 2, -4.0, -4.0, -3.0), (0.75, 0.75, math.pi / 2, 4.0, 4.0, 3.0)),
        input_box=((0.0, 0.0), (5.96, 5.96)), equilibrium=(0.0,) * 6, equilibrium_input=(hover, hover),
        angle_dims=(2,), xi_sampler=_quadrotor2d_xi, test_xi=(0.8, -2.5),
        reference_states=((0.5, 0.5, 0.5, 0.0, 0.0, 0.0), (-0.75, -0.75, -1.0, 2.0, 2.0, 2.0)),
        rl_timing=(0.02, 10.0),
        defaults=recipes.QUADROTOR2D,
        sim_dt=0.01, horizon=10.0, state_units=("m", "m", "rad", "m/s", "m/s", "rad/s"), input_units=("N", "N"),
        time_unit="s",
        description=("Planar quadrotor (Yang et al. 2024): m=0.486 kg, I=3.83 g m^2, l=25 cm, thrusts in [0, 5.96] N, "
                     "hover u*=m g/2; xi = (inertia [g m^2], arm length [cm]) shift."),
    )
