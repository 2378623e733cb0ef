"""Training for a set cut by the box (TrainConfig.exit_faces): V is held above the trained level only on the faces
where the flow may leave the box, and above the claimed level elsewhere."""

import pytest
import torch

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import PlainDecrease
from drlyap.regions import Region
from drlyap.sections import TrainSections
from drlyap.training import TrainConfig
from drlyap.training.acceptance import SetAsked, acceptance_check
from drlyap.training.states import EXIT_MARGIN, descend_on_exits, exit_speed, may_leave
from handmade import linear_pair, plain_train, small_pendulum

XI = torch.tensor([[0.0, 0.0], [0.3, 0.05]], dtype=torch.float64)


def _loop():
    system = small_pendulum()
    lyapunov, controller = linear_pair(system)
    return system, ClosedLoop(system, lyapunov, controller)


def test_may_leave_marks_the_face_states_whose_flow_points_out_at_some_sample():
    system, loop = _loop()
    region = Region.of(system, 0.1)
    z = region.sample_faces(4000, torch.Generator().manual_seed(0)).float()
    leave = may_leave(loop, XI, z, region)
    half = (region.hi - region.lo) / 2
    with torch.no_grad():  # the flow of each sample, one at a time, by the closed loop's own design model
        flows = torch.stack([loop.rhs(z, xi, model="design").double() for xi in XI])
    outward = torch.where(z.double() >= region.hi, flows, torch.where(z.double() <= region.lo, -flows, -torch.inf))
    expected = (outward > -EXIT_MARGIN * half).any(-1).any(0)
    assert torch.equal(leave, expected)
    assert 0 < int(leave.sum()) < z.shape[0]  # both kinds of face points are there
    on_upper_theta = z[:, 0].double() == region.hi[0]  # theta' = omega: the flow leaves through theta = hi where omega > 0
    assert bool(leave[on_upper_theta & (z[:, 1] > 0)].all())
    assert not bool(leave[on_upper_theta & (z[:, 1] < -EXIT_MARGIN * float(half[0]) - 1e-3)
                          & (z[:, 1].abs() < float(region.hi[1]))].any())


def test_the_faces_where_the_flow_enters_are_held_only_above_the_claimed_level():
    system = small_pendulum()
    base = dict(system=system.name, roa_level=1.0, level_margin=0.5, grow_weight=0.1)
    goal = TrainSections.of(TrainConfig(**base, exit_faces=True).resolved(system)).goal
    plain = TrainSections.of(TrainConfig(**base).resolved(system)).goal
    assert goal.level == plain.level == 1.5
    assert goal.faces_level == plain.faces_level == pytest.approx(1.575)
    assert goal.entry_faces_level == pytest.approx(1.05) and plain.entry_faces_level == plain.faces_level
    assert goal.entry_level == 1.0 and plain.entry_level == plain.level  # what the acceptance check asks there


def test_the_acceptance_check_asks_each_face_state_its_own_level():
    system, loop = _loop()
    region = Region.of(system, 0.1)
    faces = region.sample_faces(2000, torch.Generator().manual_seed(1)).float()
    values = loop.value(faces).double()
    middle = float(values.median())
    low = torch.full_like(values, middle - 1e9)
    condition = PlainDecrease(XI)

    def passed_faces(levels):
        check = acceptance_check(loop, condition, XI, region, asked=SetAsked(middle, faces, levels))
        return check.boundary_min == pytest.approx(float(values.min()), rel=1e-6), check

    same, check = passed_faces(None)  # one level for all: V's least value on the faces is below it
    assert same and check.boundary_min < middle and not check.passed
    lowered = torch.where(values <= middle, low, torch.full_like(values, middle))  # the states below it ask less
    same, lowered_check = passed_faces(lowered)
    raised = lowered.clone()
    raised[int(values.argmin())] = middle
    _, raised_check = passed_faces(raised)
    # the faces part of the verdict follows each state's level (the rest of the check is the same in all three)
    rest = lowered_check.max_violation <= 0 and lowered_check.jacobian["hurwitz"] and not lowered_check.other_equilibria
    assert lowered_check.passed == rest and not raised_check.passed


def test_exit_faces_needs_a_level_and_a_boolean():
    system = small_pendulum()  # the paper's condition: no level
    with pytest.raises(ValueError, match="exit_faces = True needs a region-of-attraction level"):
        TrainConfig(system=system.name, exit_faces=True).resolved(system)
    with pytest.raises(ValueError, match="exit_faces = 'yes' \\(must be true or false\\)"):
        TrainConfig(system=system.name, roa_level=1.0, exit_faces="yes").resolved(system)


def test_training_with_exit_faces_lets_the_set_cross_the_faces_the_flow_enters():
    """Same seed and settings with and without exit_faces: the trained set {V <= 1.5} holds more of the box once only
    the faces the flow may leave keep it in, and V stays above the claimed level 1 on every face."""
    system = small_pendulum(((-0.6, -1.2), (0.6, 1.2)))
    base = dict(system=system.name, roa_level=1.0, level_margin=0.5, grow_weight=0.3, warm_start="lqr",
                decay_rate=0.0, exp_rate=0.3, iters=60, check_every=60, n_states=512, lyapunov_hidden=[8],
                controller_hidden=[8], seed=0, xi_samples=[[0.0, 0.0], [0.05, 0.01]])
    region = Region.of(system, 0.1)
    grid = region.grid().float()
    faces = region.sample_faces(4000, torch.Generator().manual_seed(1)).float()
    shares, least = [], []
    for exits in (False, True):
        result = plain_train(TrainConfig(**base, exit_faces=exits), system, progress=False)
        with torch.no_grad():
            shares.append(float((result.lyapunov(grid) <= 1.5).double().mean()))
            least.append(float(result.lyapunov(faces).min()))
        assert result.config.exit_faces is exits
    assert shares[1] > shares[0], shares
    assert least[0] > 1.5 > least[1] > 1.0, least  # the trained set crosses the faces only with exit_faces


def test_train_prints_the_set_cut_by_the_box_and_the_command_that_searches_it():
    from drlyap.render import cut_set_line
    from drlyap.systems import get_system

    level = TrainSections.of(TrainConfig(system="quadrotor2d", level_margin=0.6).resolved(get_system("quadrotor2d"))).goal.level
    line = cut_set_line(level, (0.8, -2.5), "drlyap verify RUN")
    assert "{V <= 1.6} in the box" in line and "only where the flow may leave the box" in line
    assert "`drlyap verify RUN --xi 0.8,-2.5 --roa` searches that set cut by the box" in line


def test_descent_among_the_exits_finds_where_v_is_least_among_the_face_points_the_flow_may_leave():
    """From uniform face states, steps of descent on V with a penalty off the exits end near V's least value over the
    exits found by 200,000 face states (which a few thousand uniform states miss), and on the exits."""
    system, loop = _loop()
    region = Region.of(system, 0.1)
    dense = region.sample_faces(200_000, torch.Generator().manual_seed(2)).float()
    with torch.no_grad():
        least = float(loop.value(dense)[may_leave(loop, XI, dense, region)].min())
    z = region.sample_faces(256, torch.Generator().manual_seed(3)).float()
    with torch.no_grad():
        start = float(loop.value(z)[may_leave(loop, XI, z, region)].min())
    for _ in range(300):
        z = descend_on_exits(loop, XI, z, region)
    assert bool(((z == region.lo.float()) | (z == region.hi.float())).any(-1).all())  # still on the faces
    leave = may_leave(loop, XI, z, region)
    with torch.no_grad():
        found = float(loop.value(z)[leave].min())
    assert found < start and found == pytest.approx(least, rel=0.05, abs=1e-3), (start, found, least)
    speed = exit_speed(loop, XI, z.clone().requires_grad_(True), region)
    assert speed.shape == (256,) and torch.equal(speed.detach() > -EXIT_MARGIN, leave)


def test_exit_margin_raises_the_level_asked_where_the_flow_may_leave_and_needs_exit_faces():
    system = small_pendulum()
    base = dict(system=system.name, roa_level=1.0, level_margin=0.5, grow_weight=0.1)
    goal = TrainSections.of(TrainConfig(**base, exit_faces=True, exit_margin=0.2).resolved(system)).goal
    assert goal.faces_level == pytest.approx(1.575) and goal.exit_faces_level == pytest.approx(1.575 * 1.2)
    assert TrainSections.of(TrainConfig(**base).resolved(system)).goal.exit_faces_level is None
    with pytest.raises(ValueError, match="exit_margin = 0.2 needs exit_faces = True"):
        TrainConfig(**base, exit_margin=0.2).resolved(system)
    with pytest.raises(ValueError, match="exit_margin = -0.1 \\(must be >= 0\\)"):
        TrainConfig(**base, exit_faces=True, exit_margin=-0.1).resolved(system)


def test_on_four_states_exit_faces_trains_on_states_descended_among_the_exits():
    """A short cart-pole fit with exit_faces keeps face states moved among the exits, and the acceptance check holds
    them too; with exit_margin V's least value at those the flow may leave ends higher."""
    from drlyap.systems import get_system
    from drlyap.training.states import TrainingStates

    system = get_system("cartpole")
    base = dict(system="cartpole", level_margin=0.5, exit_faces=True, iters=100, check_every=100, n_states=256,
                lyapunov_hidden=[8], controller_hidden=[4], seed=0)
    seen = {}
    original = TrainingStates.check_faces

    def spy(self, loop, xi):
        got = original(self, loop, xi)
        seen["exits"], seen["faces"] = self.exit_minima.clone(), got[0].shape[0]
        seen["leave"] = may_leave(loop, xi, self.exit_minima, self.region)
        return got

    TrainingStates.check_faces = spy
    try:
        least = []
        for margin in (0.0, 1.0):
            result = plain_train(TrainConfig(**base, exit_margin=margin), system, progress=False)
            assert seen["faces"] == 20000 + 2 * 1024  # the uniform ones, those descended on V and among the exits
            with torch.no_grad():
                values = result.lyapunov(seen["exits"][seen["leave"]])
            least.append(float(values.min()))
    finally:
        TrainingStates.check_faces = original
    assert least[1] > least[0] + 0.4 and least[0] > 1.5, least  # the trained level 1.5, asked 1.575 and 3.15 there
