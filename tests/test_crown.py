"""The backward linear relaxation of tanh networks (enclosures/crown.py): sound against dense sampling on every range
and box tried, exact on points, and tighter than intervals where the boxes are wide."""

import torch

from drlyap.enclosures import Interval
from drlyap.enclosures.crown import mlp_layers, tanh_lines, tanh_mlp_bounds
from drlyap.networks import TanhMLP

F64 = torch.float64


def test_tanh_lines_hold_on_every_sampled_point_of_their_range():
    g = torch.Generator().manual_seed(0)
    lo = torch.cat([torch.randn(3000, generator=g, dtype=F64) * 3, torch.tensor([-40.0, 20.0, -1e-8, 0.0, -2.0],
                                                                                   dtype=F64)])
    widths = torch.tensor([0.0, 1e-10, 1e-6, 1e-3, 0.1, 1.0, 5.0, 30.0], dtype=F64)
    hi = lo + widths[torch.randint(0, len(widths), lo.shape, generator=g)]
    hi[-5:] = torch.tensor([40.0, 60.0, 1e-8, 1e-12, 2.0], dtype=F64)
    k, below, above = tanh_lines(lo, hi)
    assert bool(torch.isfinite(k).all() and torch.isfinite(below).all() and torch.isfinite(above).all())
    x = lo[:, None] + (hi - lo)[:, None] * torch.rand(lo.shape[0], 2000, generator=g, dtype=F64)
    x = torch.cat([x, lo[:, None], hi[:, None]], 1)
    gap = torch.tanh(x) - k[:, None] * x
    assert bool((gap <= above[:, None]).all() and (gap >= below[:, None]).all())
    # the chord's slope makes the lines tight on narrow ranges: the band is second order in the width
    narrow = (hi - lo) <= 1e-3
    assert float((above - below)[narrow].max()) < 1e-6


def _net(sizes, skip, seed):
    torch.manual_seed(seed)
    net = TanhMLP(sizes, [0.5 + 0.5 * i for i in range(sizes[0])], skip=skip).double()
    with torch.no_grad():
        for layer in net.layers:
            layer.bias.uniform_(-1.0, 1.0)
    return net


def test_network_bounds_hold_every_sampled_output_and_beat_intervals_on_wide_boxes():
    """Sound means sound: on 64 random boxes of each width, for a 2x16 network with a linear path and a 3x24 one,
    every output at 600 uniform points and the corners of each box lies within the bounds."""
    g = torch.Generator().manual_seed(1)
    for sizes, skip in (([3, 16, 16, 2], True), ([4, 24, 24, 24, 3], False)):
        net = _net(sizes, skip, seed=len(sizes))
        n = sizes[0]
        layers, scale, path = mlp_layers(net)
        corners = torch.cartesian_prod(*[torch.tensor([0.0, 1.0], dtype=F64)] * n)
        for width in (1e-4, 0.05, 0.5, 2.0):
            centre = torch.randn(64, n, generator=g, dtype=F64)
            lo, hi = centre - width / 2, centre + width / 2
            low, up = tanh_mlp_bounds(layers, scale, lo, hi, path)
            unit = torch.cat([torch.rand(64, 600, n, generator=g, dtype=F64), corners.expand(64, -1, -1)], 1)
            pts = lo[:, None] + (hi - lo)[:, None] * unit
            with torch.no_grad():
                values = net(pts.reshape(-1, n)).reshape(64, unit.shape[1], -1)
            assert bool((low[:, None] <= values).all() and (values <= up[:, None]).all()), (sizes, width)
            if width >= 0.5:
                iv = net(Interval(lo, hi))
                assert float((up - low).median()) < 0.5 * float((iv.hi - iv.lo).median())


def test_a_point_box_is_bounded_to_rounding():
    net = _net([2, 8, 8, 1], True, seed=3)
    z = torch.tensor([[0.3, -0.7], [0.0, 0.0]], dtype=F64)
    low, up = tanh_mlp_bounds(*mlp_layers(net)[:2], z, z, mlp_layers(net)[2])
    with torch.no_grad():
        value = net(z)
    assert bool((low <= value).all() and (value <= up).all()) and float((up - low).max()) < 1e-12
