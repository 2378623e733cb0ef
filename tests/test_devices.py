"""Bounding on a device: every tensor a proof's or the checker's bounding makes is made where its inputs are (checked
on the CPU by watching torch's factory functions), and where CUDA exists, proofs and checks on the GPU agree with the
CPU's."""

import traceback

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from torch.overrides import TorchFunctionMode

from drlyap.checker.check import LeafJob, rebuild_boxes
from drlyap.checker.model import Pair, Residual
from drlyap.closed_loop import ClosedLoop
from drlyap.compute import Compute
from drlyap.conditions import DRPointwise, TrueDecrease
from drlyap.enclosures import Interval
from drlyap.proof_settings import Budget
from drlyap.regions import Region
from drlyap.runs.certificates import PairFiles, Stated, read_certificate, sha256_file, system_digest, write_certificate
from drlyap.systems import get_system
from drlyap.training import TrainConfig, TrainSections
from drlyap.verification import verify_condition
from drlyap.verification.bounding import ConditionJob
from handmade import linear_pair, small_pendulum

F64 = torch.float64
CUDA = torch.cuda.is_available()
FACTORIES = {torch.tensor, torch.zeros, torch.ones, torch.full, torch.eye, torch.arange, torch.empty, torch.linspace,
             torch.randn, torch.rand}


class DeviceLess(TorchFunctionMode):
    """Records where drlyap's code makes a tensor without saying on which device (on a GPU it would land on the CPU)."""

    def __init__(self, allowed=()):
        super().__init__()
        self.sites, self.allowed = set(), allowed

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        # a factory without a device, or numbers made a tensor without one (a constant beside a GPU's values)
        made = (func in FACTORIES and "device" not in kwargs) or \
            (func is torch.as_tensor and not isinstance(args[0], torch.Tensor) and kwargs.get("device") is None)
        if made:
            frames = [f for f in traceback.extract_stack()[:-1] if "/src/drlyap/" in f.filename
                      and f.name not in HELPERS]
            if frames and not any(a in frames[-1].line for a in self.allowed):
                self.sites.add(f"{frames[-1].filename.split('src/')[-1]}:{frames[-1].lineno}: {frames[-1].line}")
        return func(*args, **kwargs)


# the helpers that make a constant where they are told to: the site reported is their caller
HELPERS = {"_t", "as_f64", "point", "const", "lift", "lift_pair", "join"}
# tables made once and moved to the device they are asked for, and the CPU results a job hands back
ALLOWED = (".to(device)", "torch.tensor([refined])", "torch.tensor([pieces])")


@pytest.mark.parametrize("name", ["pendulum", "mountain-car", "cartpole", "quadrotor2d"])
def test_a_proofs_bounding_makes_every_tensor_on_its_inputs_device(name):
    system = get_system(name)
    mode = DeviceLess(ALLOWED)
    for hidden in ([6], []):
        cfg = TrainConfig(system=name, lyapunov_hidden=hidden, controller_hidden=hidden).resolved(system)
        loop = ClosedLoop(system, *TrainSections.of(cfg).networks.build(system)).f64
        lo, hi = system.local_box()
        centre = lo + (hi - lo) * torch.rand(16, system.n, generator=torch.Generator().manual_seed(0), dtype=F64)
        half = (hi - lo) * 0.01
        xi = torch.zeros(3, system.k, dtype=F64)
        for condition in (DRPointwise(0.01, 0.1, xi, decay_rate=0.1), TrueDecrease(xi[:1], 0.1),
                          TrueDecrease(Interval(xi[:1] - 0.01, xi[:1] + 0.01), 0.1)):
            for enclosure in ("affine", "mean-value"):
                for level in (None, 1.0):
                    with mode:
                        ConditionJob(loop, condition, level, enclosure)(centre - half, centre + half)
    assert not mode.sites, sorted(mode.sites)


@pytest.fixture(scope="module")
def certificate(tmp_path_factory):
    system = small_pendulum()
    lyap, ctrl = linear_pair(system)
    loop = ClosedLoop(system, lyap, ctrl)
    condition = DRPointwise(0.01, 0.3, torch.tensor([[0.02, 0.01], [-0.03, 0.0]], dtype=F64), decay_rate=0.05)
    region = Region.of(system, 0.1)
    proof = verify_condition(loop, condition, region, Budget(seconds=600), level=0.5)
    assert proof.verified
    folder = tmp_path_factory.mktemp("cert")
    torch.save({"lyapunov": lyap.state_dict(), "controller": ctrl.state_dict()}, folder / "weights.pt")
    write_certificate(folder, "trained", proof, Stated(condition, region), system,
                      PairFiles(folder / "weights.pt", lyap.alpha_hat))
    return {"folder": folder, "system": system, "loop": loop, "condition": condition, "region": region,
            "proof": proof}


def _leaf_job(certificate):
    header, arrays = read_certificate(certificate["folder"], "trained")
    weights = torch.load(certificate["folder"] / "weights.pt", weights_only=True)
    claim = header["claim"]
    lo, hi = (torch.as_tensor(claim["region"][k], dtype=F64) for k in ("box_lo", "box_hi"))
    residual = Residual(claim["condition"], Pair(weights, float(header["networks"]["alpha_hat"]), 2),
                        certificate["system"])
    blo, bhi = rebuild_boxes(lo, hi, header["partition"]["grid"], arrays)
    verdict = torch.as_tensor(arrays["verdict"].astype(np.int64))
    leaves = ((verdict == 1) | (verdict == 3)).nonzero().squeeze(-1)
    return LeafJob(residual, hi - lo, 3, claim["region"]["level"], False), blo[leaves], bhi[leaves], verdict[leaves] == 3


def test_the_checkers_bounding_makes_every_tensor_on_its_inputs_device(certificate):
    job, lo, hi, above = _leaf_job(certificate)
    mode = DeviceLess(ALLOWED)
    with mode:
        out = job(lo, hi, above)
    assert bool(out["ok"].all()) and not mode.sites, sorted(mode.sites)


@pytest.mark.parametrize("name", ["cartpole", "quadrotor2d"])
def test_the_checkers_second_order_forms_make_every_tensor_on_their_inputs_device(name):
    """The checker's own forms (4 and 6 states) on a DR condition over a sublevel set, boxes bisected too."""
    from drlyap.runs.certificates import condition_claim

    system = get_system(name)
    cfg = TrainConfig(system=name, lyapunov_hidden=[6], controller_hidden=[6]).resolved(system)
    lyap, ctrl = TrainSections.of(cfg).networks.build(system)
    condition = DRPointwise(0.01, 0.1, torch.zeros(3, system.k, dtype=F64), decay_rate=0.1)
    residual = Residual(condition_claim(condition), Pair({"lyapunov": lyap.state_dict(),
                                                           "controller": ctrl.state_dict()}, lyap.alpha_hat, system.n),
                        system)
    lo, hi = system.local_box()
    centre = lo + (hi - lo) * torch.rand(8, system.n, generator=torch.Generator().manual_seed(0), dtype=F64)
    half = (hi - lo) * 0.01
    job = LeafJob(residual, hi - lo, 2, 1.0, False)
    mode = DeviceLess(ALLOWED)
    with mode:
        job(centre - half, centre + half, torch.zeros(8, dtype=torch.bool))
    assert not mode.sites, sorted(mode.sites)


def test_a_device_that_is_not_there_is_refused_in_one_line(tmp_path):
    from drlyap.cli import main

    if CUDA:
        pytest.skip("this machine has CUDA")
    out = CliRunner().invoke(main, ["check", str(tmp_path), "--device", "cuda"])
    assert out.exit_code == 2 and "no CUDA device is available here" in out.output
    with pytest.raises(ValueError, match="no CUDA device"):
        ConditionJob(None, None, None, "affine").on("cuda")


@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
def test_proofs_and_checks_on_the_gpu_agree_with_the_cpu(certificate):
    loop, condition, region = certificate["loop"], certificate["condition"], certificate["region"]
    gpu = verify_condition(loop, condition, region, Budget(seconds=600, compute=Compute(device="cuda")), level=0.5)
    assert gpu.status == certificate["proof"].status == "verified"
    job, lo, hi, above = _leaf_job(certificate)
    assert bool(job.on("cuda")(lo, hi, above)["ok"].all())
    # the GPU's bounds hold at dense samples of each box
    sub = slice(0, 256)
    bounds = ConditionJob(loop.f64, condition, None, "affine").on("cuda")(lo[sub], hi[sub])
    t = torch.rand(64, *lo[sub].shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    z = (lo[sub] + (hi[sub] - lo[sub]) * t).reshape(-1, 2)
    values = loop.exact(condition, z).reshape(64, -1)
    assert bool((values <= bounds["upper"][None] + 1e-12).all())
    folder = certificate["folder"]
    from drlyap.checker.check import LeafSettings, check_certificate

    header, arrays = read_certificate(folder, "trained")
    res = check_certificate("trained", header, arrays, certificate["system"],
                            torch.load(folder / "weights.pt", weights_only=True), sha256_file(folder / "weights.pt"),
                            system_digest(certificate["system"]), LeafSettings(compute=Compute(device="cuda")))
    assert res.ok, res.failures


def test_no_module_holds_a_tensor_made_at_import():
    """A tensor made when a module is imported lives on the CPU whatever device a proof runs on (a GPU's bounding
    then meets it in ``nextafter`` or a product and fails)."""
    import importlib
    import pkgutil

    import drlyap

    held = []
    for info in pkgutil.walk_packages(drlyap.__path__, "drlyap."):
        module = importlib.import_module(info.name)
        for key, value in vars(module).items():
            values = value if isinstance(value, (tuple, list)) else (value,)  # caches keyed by device are fine
            held += [f"{info.name}.{key}" for v in values if isinstance(v, torch.Tensor)]
    assert not held, held


@pytest.mark.skipif(not CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("name", ["pendulum", "mountain-car", "cartpole", "quadrotor2d"])
def test_every_systems_bounds_on_the_gpu_match_the_cpus_and_hold_at_samples(name):
    system = get_system(name)
    cfg = TrainConfig(system=name, lyapunov_hidden=[6], controller_hidden=[6]).resolved(system)
    loop = ClosedLoop(system, *TrainSections.of(cfg).networks.build(system)).f64
    lo, hi = system.local_box()
    g = torch.Generator().manual_seed(0)
    centre = lo + (hi - lo) * torch.rand(64, system.n, generator=g, dtype=F64)
    blo, bhi = centre - (hi - lo) * 0.01, centre + (hi - lo) * 0.01
    condition = DRPointwise(0.01, 0.1, torch.zeros(3, system.k, dtype=F64), decay_rate=0.1)
    for enclosure in ("affine", "mean-value"):
        cpu = ConditionJob(loop, condition, None, enclosure)(blo, bhi)
        gpu = ConditionJob(loop, condition, None, enclosure).on("cuda")(blo, bhi)
        assert torch.allclose(cpu["upper"], gpu["upper"], rtol=1e-9, atol=1e-9), name
        z = blo + (bhi - blo) * torch.rand(256, *blo.shape, generator=g, dtype=F64)
        values = loop.exact(condition, z.reshape(-1, system.n)).reshape(256, -1)
        assert bool((values <= gpu["upper"][None] + 1e-12).all()), name
