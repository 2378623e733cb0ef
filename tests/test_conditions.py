import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import (
    DecreaseTerms,
    DRPointwise,
    DRUniform,
    Nominal,
    PlainDecrease,
    TrueDecrease,
    cvar_bound,
    local_rates,
    make_condition,
    wasserstein_radius_guarantee,
)


def brute_force_cvar(h, eps):
    """(1/eps) inf_t [ mean_i (h_i + t)_+ - t eps ] (eq: prop_1_eq2), minimised over the breakpoints t = -h_i."""
    best = math.inf
    for t in [-v for v in h]:
        best = min(best, sum(max(v + t, 0.0) for v in h) / len(h) - t * eps)
    return best / eps


@settings(max_examples=200, deadline=None)
@given(h=st.lists(st.floats(-10, 10), min_size=1, max_size=12), eps=st.floats(0.01, 0.99))
def test_general_eps_form_matches_brute_force_cvar(h, eps):
    got = cvar_bound(torch.tensor(h, dtype=torch.float64), eps).item()
    assert got == pytest.approx(brute_force_cvar(h, eps), abs=1e-9)


def test_small_eps_reduces_to_max_and_eps_one_is_mean():
    h = torch.tensor([[3.0, -1.0, 2.0, 0.5]], dtype=torch.float64)
    assert cvar_bound(h, 0.2).item() == 3.0
    assert cvar_bound(h, 0.999).item() == pytest.approx(h.mean().item(), abs=1e-2)


def _terms(b=50, n=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    return DecreaseTerms(vdot=torch.randn(b, n, generator=g, dtype=torch.float64) - 1.0,
                         lip=torch.rand(b, generator=g, dtype=torch.float64),
                         decay=torch.rand(b, generator=g, dtype=torch.float64) * 0.1)


@pytest.mark.parametrize("cond", [Nominal(), DRPointwise(0.01, 0.1), DRPointwise(0.01, 0.5), DRUniform(0.01, 0.1),
                                  DRUniform(0.01, 0.5)])
def test_loss_is_zero_exactly_when_condition_holds(cond):
    for seed in range(20):
        terms = _terms(seed=seed)
        if isinstance(cond, Nominal):
            terms.vdot = terms.vdot[:, :1]
        # shift everything down until it holds: the loss must be zero iff max residual <= 0
        for shift in (0.0, 1.0, 3.0, 10.0):
            t = DecreaseTerms(terms.vdot - shift, terms.lip, terms.decay)
            holds = bool((cond.residual(t) <= 0).all())
            assert (cond.loss(t).item() == 0.0) == holds


def test_pointwise_residual_formula():
    terms = DecreaseTerms(vdot=torch.tensor([[-1.0, -0.5, -2.0]]), lip=torch.tensor([2.0]), decay=torch.tensor([0.1]))
    r = DRPointwise(0.01, 0.1).residual(terms)
    assert r.item() == pytest.approx(0.1 * 2.0 + (-0.5) + 0.1)


def test_uniform_uses_the_largest_lipschitz_term_over_all_states():
    vdot = torch.tensor([[-1.0, -3.0, -2.0], [-2.5, -1.5, -4.0]])
    terms = DecreaseTerms(vdot=vdot, lip=torch.tensor([0.0, 50.0]), decay=torch.zeros(2))
    r = DRUniform(0.01, 0.5).residual(terms)  # eps > 1/N: the exact single value
    h = vdot.max(0).values.tolist()  # per-sample suprema over the states: [-1, -1.5, -2]
    assert r.shape == (1,) and r.item() == pytest.approx(0.02 * 50.0 + brute_force_cvar(h, 0.5))
    r_small = DRUniform(0.01, 0.1).residual(terms)  # eps <= 1/N: per-state residual, shared Lipschitz term
    assert torch.allclose(r_small, 0.1 * 50.0 + vdot.max(1).values)


def test_make_condition_errors():
    with pytest.raises(ValueError, match="unknown method"):
        make_condition("magic", "pointwise", 0.1, 0.1)
    with pytest.raises(ValueError, match="unknown DR loss"):
        make_condition("dr", "weird", 0.1, 0.1)
    with pytest.raises(ValueError, match="risk level"):
        DRPointwise(0.1, 1.5).residual(_terms())


def test_wasserstein_radius_guarantee_cases():
    # N large: exponent 1/max(k,2)
    r = wasserstein_radius_guarantee(c1=2.0, c2=1.0, rho=1.0, k=2, n_samples=100, confidence_slack=0.1)
    assert r == pytest.approx((math.log(20.0) / 100) ** 0.5)
    # N small: exponent 1/rho
    r = wasserstein_radius_guarantee(c1=2.0, c2=0.01, rho=3.0, k=2, n_samples=5, confidence_slack=0.1)
    assert r == pytest.approx((math.log(20.0) / 0.05) ** (1 / 3))
    with pytest.raises(ValueError):
        wasserstein_radius_guarantee(1, 1, 1, 1, 5, 1.5)


def _random_pair(system, seed):
    from drlyap.training import TrainConfig, TrainSections

    torch.manual_seed(seed)
    cfg = TrainConfig(system=system.name, lyapunov_hidden=[8], lyapunov_out=4, controller_hidden=[8], init_gain=1.0)
    lyap, ctrl = TrainSections.of(cfg.resolved(system)).networks.build(system)
    return lyap.double(), ctrl.double()


@pytest.mark.parametrize("seed", [0, 1])
def test_local_rates_are_the_largest_ratio_of_vdot_to_v_next_to_x_star(seed):
    """In two states the directions of a fine circle find the largest generalised eigenvalue: the largest
    Vdot / V at radius 1e-5 must equal the rate, on the design model (DR samples) and on the true model."""
    from drlyap.systems import pendulum

    p = pendulum()
    lyap, ctrl = _random_pair(p, seed)
    xi = torch.tensor([[0.1, -0.2], [0.3, 0.0], [-0.2, 0.4]], dtype=torch.float64)
    angle = torch.linspace(0, 2 * math.pi, 20001, dtype=torch.float64)[:-1]
    z = 1e-5 * torch.stack([angle.cos(), angle.sin()], -1)
    for cond in (DRPointwise(0.01, 0.1, xi), TrueDecrease(xi)):
        rates = local_rates(cond, ClosedLoop(p, lyap, ctrl))
        with torch.no_grad():
            v = lyap(z)
            ratio = PlainDecrease(xi, model=cond.model).terms(ClosedLoop(p, lyap, ctrl), z).vdot / v[:, None]
        assert rates.shape == (3,)
        assert torch.allclose(rates, ratio.amax(0), rtol=1e-3, atol=1e-3 * float(ratio.abs().max()))


def test_local_rates_bound_vdot_over_v_in_four_states_and_carry_gradients():
    from drlyap.systems import cartpole

    c = cartpole()
    lyap, ctrl = _random_pair(c, 0)
    xi = torch.as_tensor(c.sample_xi(2, torch.Generator().manual_seed(0)), dtype=torch.float64)
    cond = PlainDecrease(xi)
    rates = local_rates(cond, ClosedLoop(c, lyap, ctrl))
    g = torch.Generator().manual_seed(1)
    d = torch.randn(20000, 4, generator=g, dtype=torch.float64)
    z = 1e-5 * d / d.norm(dim=-1, keepdim=True)
    with torch.no_grad():
        ratio = cond.terms(ClosedLoop(c, lyap, ctrl), z).vdot / lyap(z)[:, None]
    scale = float(ratio.abs().max())
    assert (ratio.amax(0) <= rates + 1e-3 * scale).all()  # no direction beats the rate
    assert (ratio.amax(0) >= rates - 0.2 * scale).all()  # and random directions come close to it
    rates.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in [*lyap.parameters(), *ctrl.parameters()])


def test_local_rates_are_nan_for_non_finite_weights():
    from drlyap.systems import pendulum

    p = pendulum()
    lyap, ctrl = _random_pair(p, 0)
    with torch.no_grad():
        lyap.phi.layers[0].weight[0, 0] = float("nan")
    rates = local_rates(TrueDecrease(torch.zeros(2, 2, dtype=torch.float64)), ClosedLoop(p, lyap, ctrl))
    assert rates.shape == (2,) and torch.isnan(rates).all()
