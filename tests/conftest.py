import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)
    yield


@pytest.fixture
def tiny_config():
    from drlyap.training import TrainConfig

    def make(**over):
        base = dict(system="pendulum", n_states=256, iters=20, check_every=20, lyapunov_hidden=[8], lyapunov_out=4,
                    controller_hidden=[8], seed=0)
        base.update(over)
        return TrainConfig(**base)

    return make
