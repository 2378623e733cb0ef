import math

import numpy as np
import torch
from scipy.integrate import solve_ivp

from drlyap.simulation import evaluate, initial_states, normalized_deviation, simulate
from drlyap.systems import mountain_car, pendulum


def pd(system, kp=30.0, kd=8.0):
    def policy(x):
        z = system.to_local(x)
        lo, hi = system.input_box
        return (-kp * z[:, :1] - kd * z[:, 1:2]).clamp(lo[0], hi[0])
    return policy


def test_rk4_matches_adaptive_integrator_on_true_model():
    p = pendulum()
    xi = torch.tensor([0.1, 0.05], dtype=torch.float64)
    policy = pd(p)
    x0 = torch.tensor([[1.0, -2.0]], dtype=torch.float64)
    traj = simulate(p, policy, x0, xi, dt=0.01, horizon=3.0)

    def rhs(t, y):
        x = torch.tensor(y[None], dtype=torch.float64)
        return p.true_dynamics(x, policy(x), xi)[0].numpy()

    ref = solve_ivp(rhs, (0, 3.0), x0[0].numpy(), rtol=1e-10, atol=1e-10, t_eval=traj.t.numpy())
    assert np.allclose(ref.y.T, traj.x[:, 0].numpy(), atol=1e-5)


def test_batched_simulation_equals_one_by_one():
    p = pendulum()
    xi = torch.tensor([0.1, 0.05], dtype=torch.float64)
    x0 = initial_states(p, 6, torch.Generator().manual_seed(0))
    batch = simulate(p, pd(p), x0, xi, horizon=1.0)
    for i in range(6):
        single = simulate(p, pd(p), x0[i:i + 1], xi, horizon=1.0)
        assert torch.allclose(single.x[:, 0], batch.x[:, i], atol=1e-12)


def test_evaluation_uses_the_true_shift_and_scores_success():
    p = pendulum()
    x0 = initial_states(p, 20, torch.Generator().manual_seed(1))
    strong = evaluate(p, pd(p), x0, torch.tensor([0.1, 0.05]), lyapunov=lambda x: (p.to_local(x) ** 2).sum(-1))
    assert strong["n"] == 20 and strong["n_success"] == strong["n"] and strong["success_rate"] == 1.0
    none = evaluate(p, lambda x: torch.zeros(x.shape[0], 1, dtype=x.dtype), x0, torch.tensor([0.1, 0.05]))
    assert none["n_success"] == 0  # an unactuated pendulum falls from every state
    # a heavy enough pendulum cannot be held by a weak saturated controller: the shift matters
    weak = lambda x: pd(p, kp=11.0, kd=3.0)(x).clamp(-10.5, 10.5)  # noqa: E731
    up = torch.tensor([[1.4, 0.0]], dtype=torch.float64)
    assert evaluate(p, weak, up, None)["n_success"] == 1
    assert evaluate(p, weak, up, torch.tensor([0.2, 0.0]))["n_success"] == 0


def test_angles_count_modulo_two_pi():
    p = pendulum()
    x = torch.tensor([[2 * math.pi + 0.001, 0.0], [0.5, 0.0]], dtype=torch.float64)
    d = normalized_deviation(p, x)
    assert d[0] < 1e-3 and d[1] > 0.1


def test_mountain_car_equilibrium_is_at_the_hill_top():
    mc = mountain_car()
    x = torch.tensor([[math.pi / 6, 0.0]], dtype=torch.float64)
    assert mc.true_dynamics(x, torch.zeros(1, 1, dtype=torch.float64)).abs().max() < 1e-15
