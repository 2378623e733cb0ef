"""Figures: phase portraits of closed-loop trajectories and certificate / input time series.

All functions take already simulated data and write one PNG; they never simulate or train.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from torch import Tensor  # noqa: E402

from drlyap.simulation import Trajectories  # noqa: E402
from drlyap.systems import UncertainSystem  # noqa: E402


def _display_states(system: UncertainSystem, x: Tensor) -> Tensor:
    """States ``(T, B, n)`` with angles wrapped into the box; NaN breaks lines at wrap jumps."""
    shape = x.shape
    shown = system.to_user(system.to_local(x.reshape(-1, system.n))).reshape(shape).clone()
    if system.angle_dims and shape[0] > 1:
        idx = list(system.angle_dims)
        jump = (shown[1:, :, idx] - shown[:-1, :, idx]).abs().amax(-1) > 3.0
        shown[1:][jump] = float("nan")
    return shown


def _save(fig, path: Path, title: str = "") -> Path:
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def phase_portraits(system: UncertainSystem, panels: Mapping[str, Trajectories], success: Mapping[str, Sequence[bool]],
                    path: Path, title: str = "", levels: Mapping[str, tuple[Tensor, Tensor, Tensor]] | None = None) -> Path:
    """One phase-plane panel per controller (first two state coordinates): trajectories, starts
    (green dots), ends (red crosses), x* (black star); optional V contours ``(X, Y, V)`` per panel."""
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.4), squeeze=False)
    lo, hi = system.state_box
    for ax, (label, traj) in zip(axes[0], panels.items()):
        if levels and label in levels:
            gx, gy, gv = levels[label]
            ax.contour(gx, gy, gv, levels=12, colors="0.8", linewidths=0.6)
        x = _display_states(system, traj.x)
        ok = list(success[label])
        for b in range(x.shape[1]):
            ax.plot(x[:, b, 0], x[:, b, 1], lw=0.9, color="tab:blue" if ok[b] else "tab:orange")
        ax.plot(traj.x[0, :, 0], traj.x[0, :, 1], "o", color="tab:green", ms=5, label="start")
        ax.plot(x[-1, :, 0], x[-1, :, 1], "x", color="tab:red", ms=7, label="end")
        ax.plot(*system.equilibrium[:2], "*", color="black", ms=11, label="x*")
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_xlabel(system.state_names[0])
        ax.set_ylabel(system.state_names[1])
        ax.set_title(f"{label}: {sum(ok)}/{len(ok)} stabilised")
        ax.legend(loc="upper right", fontsize=8)
    return _save(fig, path, title)


def time_series(series: Mapping[str, tuple[Tensor, Tensor, Tensor]], path: Path, title: str = "",
                value_label: str = "V(x(t))", input_label: str = "u(t)") -> Path:
    """Two panels: certificate (or value) along the trajectory and the input, per controller.

    ``series[label] = (t (T,), value (T,), u (T,))``.
    """
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    positive = all(bool((value > 0).all()) for _, value, _ in series.values())
    for label, (t, value, u) in series.items():
        a.plot(t, value, label=label)
        b.plot(t, u, label=label)
    a.set_xlabel("t")
    a.set_ylabel(value_label)
    a.set_yscale("log" if positive else "symlog")
    if positive:  # at most ten decades: a certificate that reaches 1e-35 would flatten all the others
        low = min(float(v.min()) for _, v, _ in series.values())
        high = max(float(v.max()) for _, v, _ in series.values())
        a.set_ylim(bottom=max(low, 1e-10 * high))
    b.set_xlabel("t")
    b.set_ylabel(input_label)
    a.legend()
    b.legend()
    return _save(fig, path, title)


def lyapunov_grid(system: UncertainSystem, lyapunov, per_axis: int = 120) -> tuple[Tensor, Tensor, Tensor]:
    """``(X, Y, V)`` on a grid of the first two coordinates (others at x*), for contour plots."""
    lo, hi = system.state_box
    gx, gy = torch.meshgrid(torch.linspace(lo[0], hi[0], per_axis, dtype=torch.float64),
                            torch.linspace(lo[1], hi[1], per_axis, dtype=torch.float64), indexing="xy")
    x = torch.tensor(system.equilibrium, dtype=torch.float64).repeat(gx.numel(), 1)
    x[:, 0], x[:, 1] = gx.reshape(-1), gy.reshape(-1)
    return gx, gy, lyapunov(x).reshape(gx.shape)


def sweep_plot(system_name: str, factors: Sequence[int], results: Sequence[dict], path: Path,
               test_xi: Sequence[float]) -> Path:
    """Success rate against the size of the parameter shift (multiples of the test shift), per method;
    one thin line per seed and the mean as a thick line."""
    fig, ax = plt.subplots(figsize=(6, 4))
    colors = {"baseline": "tab:orange", "dr": "tab:blue"}
    for method, color in colors.items():
        rows = [r for r in results if r["method"] == method]
        if not rows:
            continue
        rates = torch.tensor([[r["sweep_200"][k] / r["more_200"]["n"] for k in factors] for r in rows])
        for line in rates:
            ax.plot(factors, line, color=color, alpha=0.3, lw=0.8)
        ax.plot(factors, rates.mean(0), color=color, lw=2.5, marker="o", label=f"{method} (mean of {len(rows)} seeds)")
    ax.set_xlabel(f"shift = k x test shift {list(test_xi)}")
    ax.set_ylabel("success rate on the true model")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xticks(list(factors))
    ax.set_title(f"{system_name}: robustness to larger parameter shifts")
    ax.legend()
    return _save(fig, path)


def against_radius(summary: Sequence[dict], factors: Sequence[float], path: Path, title: str = "") -> Path:
    """A sweep's outcome against the Wasserstein radius r, one line per risk level eps (method ``dr``),
    the baseline (which ignores r) as a dashed level; lines are means over seeds, bands their min-max.

    ``summary`` is :func:`drlyap.sweep.summarise`'s list; panels: success at the first and last shift
    factor, share of seeds whose decrease at the test shift is verified, share of X_delta where it is
    proved (a lower bound when the branch and bound stopped on its time limit; its own y-range),
    certified region of attraction.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    first, last = f"{factors[0]:g}", f"{factors[-1]:g}"
    panels = [(f"success at {first}x test shift", lambda s: s["success"][first]),
              (f"success at {last}x test shift", lambda s: s["success"][last]),
              ("decrease at test shift verified (share of seeds)",
               lambda s: dict.fromkeys(("mean", "min", "max"), s["test_verified"] / (s["n"] - s["failed"]))),
              ("share of X_delta where that decrease is proved", lambda s: s["test_verified_fraction"]),
              ("certified ROA (share of the box)", lambda s: s["roa_share"])]
    done = [s for s in summary if s["n"] > s["failed"]]
    radii = sorted({s["radius"] for s in done if s["radius"] is not None}) or [0.0]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.9 * len(panels), 3.8), squeeze=False)
    for ax, (label, get) in zip(axes[0], panels):
        for eps in sorted({s["eps"] for s in done if s["method"] == "dr"}):
            rows = sorted((s for s in done if s["method"] == "dr" and s["eps"] == eps), key=lambda s: s["radius"])
            r = [s["radius"] for s in rows]
            stats = [get(s) for s in rows]
            line = ax.plot(r, [v["mean"] for v in stats], marker="o", label=f"DR eps={eps:g}")[0]
            ax.fill_between(r, [v["min"] for v in stats], [v["max"] for v in stats], color=line.get_color(), alpha=0.2)
        for s in (s for s in done if s["method"] == "baseline"):
            v = get(s)
            ax.axhline(v["mean"], color="black", ls="--", lw=1, label="baseline (no r)")
            ax.axhspan(v["min"], v["max"], color="black", alpha=0.08)
        ax.set_xlabel("Wasserstein radius r")
        ax.set_title(label, fontsize=9)
        if label.startswith("share of X_delta"):
            ax.margins(y=0.1)
        else:
            ax.set_ylim(-0.03, 1.03)
        ax.set_xticks(radii)
        ax.tick_params(axis="x", labelrotation=45)
    axes[0][0].legend(fontsize=8)
    return _save(fig, path, title)
