"""Gymnasium environments built from the true models."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

gymnasium = pytest.importorskip("gymnasium")  # part of the optional extra drlyap[rl]

from gymnasium.utils.env_checker import check_env  # noqa: E402

from drlyap.rl.envs import ENV_IDS, UncertainSystemEnv, make_env, observe, reward_weights  # noqa: E402
from drlyap.simulation import rk4_step  # noqa: E402
from drlyap.systems import get_system  # noqa: E402

torch.set_num_threads(1)


@pytest.mark.parametrize("env_id", sorted(ENV_IDS))
def test_check_env_passes(env_id):
    env = gymnasium.make(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the checker recommends normalised action boxes; ours are physical
        check_env(env.unwrapped, skip_render_check=True)
    assert env.unwrapped.system.name == ENV_IDS[env_id]


def test_make_with_xi_and_timing():
    env = gymnasium.make("drlyap/Pendulum-v0", xi=(0.1, 0.05))
    base = env.unwrapped
    assert base.xi.tolist() == [0.1, 0.05]
    assert base.dt == 0.05 and base.max_steps == 200
    assert make_env("mountain-car").xi.tolist() == [0.0]
    with pytest.raises(ValueError, match="takes 2 xi"):
        make_env("pendulum", xi=[0.1])
    with pytest.raises(ValueError, match="unknown system"):
        make_env("no-such-system")


def test_pendulum_reward_formula_wrapped():
    env = make_env("pendulum")
    theta, omega, u = 2 * math.pi - 0.4, 1.5, 20.0  # angle wraps to -0.4; torque clipped to 15
    env.reset(seed=0, options={"state": [theta, omega]})
    _, reward, terminated, truncated, _ = env.step(np.array([u], dtype=np.float32))
    assert reward == pytest.approx(-(0.4**2 + 0.1 * omega**2 + 0.001 * 15.0**2))
    assert not terminated and not truncated


def test_generic_reward_formula():
    env = make_env("mountain-car")
    s = get_system("mountain-car")
    wx, wu = reward_weights(s)
    assert np.allclose(wx, [1 / 4, 1 / 0.16]) and np.allclose(wu, [0.001 / 4])
    x = np.array([0.0, 0.1])
    env.reset(options={"state": x})
    _, reward, *_ = env.step(np.array([1.0], dtype=np.float32))
    z = x - np.array(s.equilibrium)
    assert reward == pytest.approx(-((z[0] / 2) ** 2 + (z[1] / 0.4) ** 2 + 0.001 * (1.0 / 2) ** 2))


def test_step_is_rk4_of_true_model_and_xi_matters():
    s = get_system("pendulum")
    x0 = np.array([0.5, -1.0])
    nexts = {}
    for xi in ((0.0, 0.0), (0.1, 0.05)):
        env = make_env("pendulum", xi=xi)
        env.reset(options={"state": x0})
        env.step(np.array([2.0], dtype=np.float32))
        ref = rk4_step(lambda x, xi=xi: s.true_dynamics(x, torch.tensor([[2.0]], dtype=torch.float64),
                                                        torch.tensor(xi, dtype=torch.float64)),
                       torch.from_numpy(x0).reshape(1, -1), 0.05)[0].numpy()
        assert np.allclose(env.state, ref, atol=1e-12)
        nexts[xi] = env.state
    assert np.abs(nexts[(0.0, 0.0)] - nexts[(0.1, 0.05)]).max() > 1e-4


def test_truncation_observation_and_reset_box():
    env = UncertainSystemEnv("pendulum", episode_time=0.2)
    obs, _ = env.reset(seed=3)
    lo, hi = get_system("pendulum").test_box
    assert np.all(obs >= np.array(lo, dtype=np.float32)) and np.all(obs <= np.array(hi, dtype=np.float32))
    truncated = False
    for _ in range(env.max_steps):
        assert not truncated
        obs, _, _, truncated, _ = env.step(env.action_space.sample())
    assert truncated and env.max_steps == 4
    # observations wrap angles and clip into the state box; the physical state is not clipped
    x = torch.tensor([[3 * math.pi / 2, 20.0], [0.1, -0.2]], dtype=torch.float64)
    o = observe(get_system("pendulum"), x)
    assert o.dtype == np.float32
    assert np.allclose(o[0], [-math.pi / 2, 8.0]) and np.allclose(o[1], [0.1, -0.2])


def test_reset_is_seeded():
    a, b = make_env("mountain-car"), make_env("mountain-car")
    assert np.array_equal(a.reset(seed=5)[0], b.reset(seed=5)[0])
