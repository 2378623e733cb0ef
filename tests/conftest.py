import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _own_seal_key(tmp_path_factory):
    """The tests' seals use a key of their own (:mod:`drlyap.seal`), not the user's."""
    import os

    os.environ["DRLYAP_STATE_DIR"] = str(tmp_path_factory.mktemp("state"))
    yield


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
