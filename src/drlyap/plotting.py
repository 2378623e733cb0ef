"""Drawing: phase portraits of closed-loop trajectories, certificate / input time series, maps and sweep plots.

All functions take already simulated data and write one PNG; they never simulate or train.
"""

from __future__ import annotations

import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from matplotlib.colors import LogNorm, TwoSlopeNorm  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
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
    if not fig.get_layout_engine():
        fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- labels
def unit_label(name: str, unit: str = "") -> str:
    """``theta [rad]``, or the bare name when the unit is unknown."""
    return f"{name} [{unit}]" if unit else name


def state_label(system: UncertainSystem, i: int) -> str:
    """Axis label of state coordinate ``i`` with its unit."""
    return unit_label(system.state_names[i], system.state_units[i] if system.state_units else "")


def input_label(system: UncertainSystem, j: int | None = None) -> str:
    """Axis label of input coordinate ``j`` with its unit; ``None``: all inputs (``u(t) = torque [N m]`` for
    one input, ``u(t) [N]`` for several sharing a unit)."""
    if j is None and system.m == 1:
        j = 0
    if j is not None:
        return unit_label(f"u(t) = {system.input_names[j]}", system.input_units[j] if system.input_units else "")
    units = set(system.input_units)
    return unit_label("u(t)", units.pop() if len(units) == 1 else "")


def time_label(system: UncertainSystem) -> str:
    return unit_label("t", system.time_unit)


def input_limits(system: UncertainSystem, j: int | None = None) -> list[tuple[float, str]]:
    """The input set's bounds as ``[(value, label)]``, ``u_max`` then ``u_min``, for coordinate ``j`` or (``None``)
    for every input (each distinct pair once, named by its inputs when there are several)."""
    lo, hi = system.input_box
    pairs: dict[tuple[float, float], list[int]] = {}
    for i in range(system.m) if j is None else [j]:
        pairs.setdefault((hi[i], lo[i]), []).append(i)
    out = []
    for (top, bottom), idx in pairs.items():
        unit = f" {system.input_units[idx[0]]}" if system.input_units else ""
        names = "" if system.m == 1 or j is not None else f" ({', '.join(system.input_names[i] for i in idx)})"
        out += [(top, f"u_max = {top:g}{unit}{names}"), (bottom, f"u_min = {bottom:g}{unit}{names}")]
    return out


def input_limits_of(systems: Sequence[UncertainSystem], j: int | None = None) -> list[tuple[float, str]]:
    """:func:`input_limits` of several systems drawn on one plot: each distinct bound once, named by its
    system when the systems' bounds differ (``pendulum-u9: u_max = 9 N m``)."""
    distinct: dict[tuple, UncertainSystem] = {}
    for system in systems:
        distinct.setdefault(tuple(tuple(b) if j is None else b[j] for b in system.input_box), system)
    if len(distinct) <= 1:
        return input_limits(systems[0], j) if systems else []
    return [(value, f"{system.name}: {text}") for system in distinct.values() for value, text in input_limits(system, j)]


def shift_text(system: UncertainSystem, xi: Sequence[float] | Tensor | None) -> str:
    """``xi = (mass +0.1, damping +0.05)``, or ``nominal model (xi = 0)``."""
    if xi is None:
        return "nominal model (xi = 0)"
    values = torch.as_tensor(xi, dtype=torch.float64).reshape(-1).tolist()
    return "xi = (" + ", ".join(f"{n} {v:+g}" for n, v in zip(system.uncertain, values)) + ")"


# --------------------------------------------------------------------------- phase portraits
def _contour_levels(values: Tensor, count: int = 8) -> list[float]:
    """Increasing V levels at quantiles of ``values`` (so that they spread over the plane), 2 digits."""
    finite = values[torch.isfinite(values)].reshape(-1)
    if finite.numel() == 0:
        return []
    qs = torch.quantile(finite[:: max(1, finite.numel() // 20000)],
                        torch.linspace(0.03, 0.85, count, dtype=finite.dtype)).tolist()
    levels = sorted({float(f"{q:.2g}") for q in qs if q > 0})
    return levels


def draw_phase(ax, system: UncertainSystem, traj: Trajectories | None, success: Sequence[bool] | None,
               grid: tuple[Tensor, Tensor, Tensor] | None = None, region: Mapping | None = None,
               delta: float | None = None) -> None:
    """One phase-plane panel (the system's ``plot_dims``; with more than two states the V contours are a slice
    through x* and the trajectories are projections) on ``ax``: labelled V contours of
    ``grid = (X, Y, V)``, the set ``region = {"level": c, "label": str, "certified": bool}`` filled (green
    when certified, grey hatched otherwise), trajectories coloured by success (one legend entry per
    colour), starts, ends, x*, the delta-ball and the state box."""
    lo, hi = system.state_box
    i, j = system.plot_dims
    if grid is not None:
        gx, gy, gv = grid
        levels = _contour_levels(gv)
        if region and region.get("level"):
            levels = [lv for lv in levels if abs(lv - region["level"]) > 0.05 * region["level"]]
        if levels:
            cs = ax.contour(gx, gy, gv, levels=levels, colors="0.55", linewidths=0.7)
            ax.clabel(cs, fmt=lambda v: f"V={v:.2g}", fontsize=7, inline=True)
        if region and region.get("level"):
            c = float(region["level"])
            ok = bool(region.get("certified"))
            color = "tab:green" if ok else "0.4"
            ax.contourf(gx, gy, gv, levels=[float(gv.min()) - 1.0, c], colors=[color], alpha=0.18 if ok else 0.12,
                        hatches=[None] if ok else ["//"])
            ax.contour(gx, gy, gv, levels=[c], colors=[color], linewidths=2.0, linestyles="solid" if ok else "dashed")
            ax.plot([], [], color=color, lw=6, alpha=0.4, label=textwrap.fill(region["label"], 75))
    if delta:
        _draw_ball(ax, system, delta, label=f"delta-ball (|x - x*| < {delta:g}, excluded from the proof)")
    if traj is not None:
        x = _display_states(system, traj.x)
        ok = [bool(v) for v in (success if success is not None else [True] * x.shape[1])]
        for flag, color, text in ((True, "tab:blue", "stabilised"), (False, "tab:orange", "not stabilised")):
            idx = [b for b in range(x.shape[1]) if ok[b] == flag]
            for k, b in enumerate(idx):
                ax.plot(x[:, b, i], x[:, b, j], lw=0.9, color=color,
                        label=f"{text} ({len(idx)} of {len(ok)})" if k == 0 else None)
        ax.plot(x[0, :, i], x[0, :, j], "o", color="tab:green", ms=4, label="start")
        ax.plot(x[-1, :, i], x[-1, :, j], "x", color="tab:red", ms=6, label="end")
    ax.plot(system.equilibrium[i], system.equilibrium[j], "*", color="black", ms=11, label="x*")
    ax.add_patch(Rectangle((lo[i], lo[j]), hi[i] - lo[i], hi[j] - lo[j], fill=False, lw=1.5, color="black"))
    pad0, pad1 = 0.03 * (hi[i] - lo[i]), 0.03 * (hi[j] - lo[j])
    ax.set_xlim(lo[i] - pad0, hi[i] + pad0)
    ax.set_ylim(lo[j] - pad1, hi[j] + pad1)
    ax.set_xlabel(state_label(system, i))
    ax.set_ylabel(state_label(system, j))
    _note_slice(ax, system, projected=traj is not None)


def phase_portrait(system: UncertainSystem, traj: Trajectories, success: Sequence[bool], path: Path, title: str = "",
                   grid: tuple[Tensor, Tensor, Tensor] | None = None, region: Mapping | None = None,
                   delta: float | None = None) -> Path:
    """A single phase portrait (:func:`draw_phase`) with its legend below the axes."""
    fig, ax = plt.subplots(figsize=(7.5, 7.2), layout="constrained")
    draw_phase(ax, system, traj, success, grid, region, delta)
    fig.legend(loc="outside lower center", ncol=2, fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)


def phase_portraits(system: UncertainSystem, panels: Mapping[str, Trajectories], success: Mapping[str, Sequence[bool]],
                    path: Path, title: str = "", levels: Mapping[str, tuple[Tensor, Tensor, Tensor]] | None = None,
                    regions: Mapping[str, Mapping] | None = None) -> Path:
    """One phase-plane panel per controller (:func:`draw_phase`); one legend below the panels."""
    fig, axes = plt.subplots(1, len(panels), figsize=(5.6 * len(panels), 5.6), squeeze=False, layout="constrained")
    for ax, (label, traj) in zip(axes[0], panels.items()):
        ok = list(success[label])
        region = (regions or {}).get(label)
        if region:  # one legend for all panels: say whose set it is
            region = {**region, "label": f"{label}: {region['label']}"}
        draw_phase(ax, system, traj, ok, (levels or {}).get(label), region)
        ax.set_title(f"{label}: {sum(ok)}/{len(ok)} stabilised")
    handles = {}
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            key = lab.split(" (")[0] if lab.startswith(("stabilised", "not stabilised")) else lab
            handles.setdefault(key, h)
    long = any(len(text) > 40 for text in handles)
    fig.legend(list(handles.values()), list(handles), loc="outside lower center",
               ncol=min(2 if long else 5, len(handles)), fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


# --------------------------------------------------------------------------- time series
def time_series_figure(series: Mapping[str, tuple[Tensor, Tensor, Tensor]], title: str = "",
                       value_label: str = "V(x(t))", input_label: str = "u(t)", time_label: str = "t",
                       limits: Sequence[tuple[float, str]] = (), input_names: Sequence[str] = ()):
    """The figure of :func:`time_series` (returned, not saved): axes 0 the certificate, axes 1 the input
    with the input limits ``limits = [(value, label)]`` as dashed horizontal lines. Several inputs
    (``u`` of shape ``(T, m)``) share a colour per series and differ in line style (``input_names``)."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.6), layout="constrained")
    positive = all(bool((value > 0).all()) for _, value, _ in series.values())
    styles = ("-", "--", ":", "-.")
    inputs = 1
    for label, (t, value, u) in series.items():
        line = a.plot(t, value, label=label)[0]
        u = u.reshape(len(t), -1)
        inputs = max(inputs, u.shape[1])
        for k in range(u.shape[1]):
            b.plot(t, u[:, k], color=line.get_color(), ls=styles[k % len(styles)])
    if inputs > 1:
        for k, name in enumerate(input_names):
            b.plot([], [], color="0.3", ls=styles[k % len(styles)], label=name)
        b.legend(fontsize=7, loc="upper left")
    a.set_xlabel(time_label)
    a.set_ylabel(value_label)
    a.set_yscale("log" if positive else "symlog")
    if positive:  # at most ten decades: a certificate that reaches 1e-35 would flatten all the others
        low = min(float(v.min()) for _, v, _ in series.values())
        high = max(float(v.max()) for _, v, _ in series.values())
        a.set_ylim(bottom=max(low, 1e-10 * high))
    colors = ("tab:red", "tab:brown", "tab:pink", "tab:purple")
    for i, (value, text) in enumerate(limits):  # one colour per (u_max, u_min) pair
        color = colors[(i // 2) % len(colors)]
        b.axhline(value, ls="--", lw=1.2, color=color, label=text)
        upper = i % 2 == 0  # u_max above its line, u_min below
        b.annotate(text, (1.0, value), xycoords=("axes fraction", "data"), xytext=(-4, 3 if upper else -3),
                   textcoords="offset points", ha="right", va="bottom" if upper else "top", color=color, fontsize=8)
    if limits:
        values = [v for v, _ in limits] + [float(u.min()) for _, _, u in series.values()] + \
            [float(u.max()) for _, _, u in series.values()]
        span = max(values) - min(values)
        b.set_ylim(min(values) - 0.1 * span, max(values) + 0.1 * span)
    b.set_xlabel(time_label)
    b.set_ylabel(input_label)
    fig.legend(handles=a.lines, loc="outside lower center", ncol=min(3, len(series)), fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


def time_series(series: Mapping[str, tuple[Tensor, Tensor, Tensor]], path: Path, title: str = "",
                value_label: str = "V(x(t))", input_label: str = "u(t)", time_label: str = "t",
                limits: Sequence[tuple[float, str]] = (), input_names: Sequence[str] = ()) -> Path:
    """Two panels: certificate (or value) along the trajectory and the input with its limits, per
    controller or start state (one legend below both panels).

    ``series[label] = (t (T,), value (T,), u (T,) or (T, m))``; ``limits`` as :func:`input_limits`;
    ``input_names`` name the line styles of several inputs.
    """
    return _save(time_series_figure(series, title, value_label, input_label, time_label, limits, input_names), path)


def states_over_time(system: UncertainSystem, series: Mapping[str, tuple[Tensor, Tensor]], path: Path,
                     title: str = "") -> Path:
    """One panel per state coordinate (with its unit) against time, one line per controller, x* dashed.

    ``series[label] = (t (T,), x (T, n))`` in user coordinates (angles wrapped into the box).
    """
    n = system.n
    cols = 2 if n > 1 else 1
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(5.5 * cols, 2.4 * rows + 0.8), squeeze=False, sharex=True,
                             layout="constrained")
    flat = axes.reshape(-1)
    for label, (t, x) in series.items():
        shown = _display_states(system, x.reshape(len(t), 1, n))[:, 0]
        for d in range(n):
            flat[d].plot(t, shown[:, d], label=label if d == 0 else None)
    for d in range(n):
        flat[d].axhline(system.equilibrium[d], ls="--", lw=0.8, color="0.4")
        flat[d].set_ylabel(state_label(system, d))
    for ax in flat[n:]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel(time_label(system))
    fig.legend(loc="outside lower center", ncol=min(4, max(1, len(series))), fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plane_states(system: UncertainSystem, gx: Tensor, gy: Tensor) -> Tensor:
    """States ``(G, n)`` of the plotted plane: ``gx``, ``gy`` on the ``plot_dims`` coordinates, x* elsewhere."""
    i, j = system.plot_dims
    x = torch.tensor(system.equilibrium, dtype=torch.float64).repeat(gx.numel(), 1)
    x[:, i], x[:, j] = gx.reshape(-1), gy.reshape(-1)
    return x


def lyapunov_grid(system: UncertainSystem, lyapunov, per_axis: int = 120) -> tuple[Tensor, Tensor, Tensor]:
    """``(X, Y, V)`` on a grid of the ``plot_dims`` coordinates (others at x*), for contour plots.

    An angle coordinate stops just short of the box's upper edge, where it wraps to the lower one.
    """
    lo, hi = system.state_box
    ends = [hi[d] - (1e-9 * (hi[d] - lo[d]) if d in system.angle_dims else 0.0) for d in system.plot_dims]
    i, j = system.plot_dims
    gx, gy = torch.meshgrid(torch.linspace(lo[i], ends[0], per_axis, dtype=torch.float64),
                            torch.linspace(lo[j], ends[1], per_axis, dtype=torch.float64), indexing="xy")
    return gx, gy, lyapunov(plane_states(system, gx, gy)).reshape(gx.shape)


def _note_slice(ax, system: UncertainSystem, projected: bool = False) -> None:
    """On a plane of an n > 2 system, say what it holds fixed (``slice with (x, x_dot) at x*``) and, with
    ``projected``, that trajectories are projections onto it."""
    if system.n <= 2:
        return
    rest = [system.state_names[d] for d in range(system.n) if d not in system.plot_dims]
    text = f"slice with ({', '.join(rest)}) at x*" + ("; trajectories projected" if projected else "")
    ax.text(0.01, 0.99, text, transform=ax.transAxes, va="top", fontsize=7, color="0.3")


def _draw_ball(ax, system: UncertainSystem, delta: float, label: str | None = None) -> None:
    """The delta-ball's outline in the ``plot_dims`` plane (its section through x*)."""
    i, j = system.plot_dims
    t = torch.linspace(0, 2 * torch.pi, 100)
    ax.plot(system.equilibrium[i] + delta * torch.cos(t), system.equilibrium[j] + delta * torch.sin(t), ":",
            color="black", lw=0.9, label=label)


def decrease_map(system: UncertainSystem, grid: tuple[Tensor, Tensor, Tensor], residual: Tensor, path: Path,
                 title: str = "", condition: str = "Vdot + gamma |x - x*|", delta: float | None = None) -> Path:
    """Two heatmaps over the ``plot_dims`` coordinates (others at x*): V, and the decrease residual
    ``residual (same shape as V; NaN where excluded, e.g. the delta-ball)`` on a colour scale centred at
    0, where it is > 0 (the condition fails) outlined in black and counted in the title."""
    gx, gy, gv = (g.detach().cpu() for g in grid)
    i, j = system.plot_dims
    residual = residual.detach().cpu()
    px, py = gx.numpy(), gy.numpy()  # matplotlib takes arrays
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 5.2), layout="constrained")
    v_top = float(gv.max())
    m = a.pcolormesh(px, py, gv.clamp_min(1e-4 * v_top).numpy(), shading="auto", cmap="viridis",
                     norm=LogNorm(vmin=max(float(gv.min()), 1e-4 * v_top), vmax=v_top))
    fig.colorbar(m, ax=a, label="V(x) (log scale)")
    levels = _contour_levels(gv)
    if levels:
        cs = a.contour(px, py, gv.numpy(), levels=levels, colors="white", linewidths=0.6)
        a.clabel(cs, fmt=lambda v: f"V={v:.2g}", fontsize=7)
    finite = residual[torch.isfinite(residual)]
    norm = TwoSlopeNorm(vcenter=0.0, vmin=min(-1e-12, float(finite.min())), vmax=max(1e-12, float(finite.max())))
    r = b.pcolormesh(px, py, residual.numpy(), shading="auto", cmap="RdBu_r", norm=norm)
    fig.colorbar(r, ax=b, label=f"{condition} (> 0: fails)")
    fails = residual > 0  # NaN (the excluded delta-ball) is not a failure
    if delta:
        for ax in (a, b):
            _draw_ball(ax, system, delta)
    if bool(fails.any()):
        b.contour(px, py, fails.double().numpy(), levels=[0.5], colors="black", linewidths=1.0)
    share = float(fails.double().sum() / max(1, finite.numel()))
    for ax in (a, b):
        ax.plot(system.equilibrium[i], system.equilibrium[j], "*", color="white" if ax is a else "black", ms=10)
        ax.set_xlabel(state_label(system, i))
        ax.set_ylabel(state_label(system, j))
        _note_slice(ax, system)
    a.set_title("Lyapunov function V")
    where = "outside the delta-ball" if delta else ""
    top = float(finite.max()) if finite.numel() else float("nan")
    verdict = (f"decrease fails (> 0, outlined) on {100 * share:.2f}% of the grid {where}" if share > 0
               else f"decrease holds at every grid point {where}")
    b.set_title(f"{verdict}\n(max {top:.3g} on the grid; grid values, not a proof)", fontsize=9)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def sweep_plot(system_name: str, factors: Sequence[int], results: Sequence[dict], path: Path,
               test_xi: Sequence[float]) -> Path:
    """Success rate against the size of the parameter shift (multiples of the test shift), per method:
    every seed as a dot (methods side by side), the min-max band over seeds and the mean as a line."""
    fig, ax = plt.subplots(figsize=(7, 5), layout="constrained")
    colors = {"baseline": "tab:orange", "dr": "tab:blue"}
    offsets = {"baseline": -0.08, "dr": 0.08}
    for method, color in colors.items():
        rows = [r for r in results if r["method"] == method]
        if not rows:
            continue
        rates = torch.tensor([[r["sweep_200"][k] / r["more_200"]["n"] for k in factors] for r in rows],
                             dtype=torch.float64)
        xs = torch.tensor([float(k) for k in factors]) + offsets[method]
        ax.fill_between(xs, rates.amin(0), rates.amax(0), color=color, alpha=0.15, lw=0)
        for line in rates:
            ax.plot(xs, line, "o", color=color, ms=4, alpha=0.7, mfc="none")
        ax.plot(xs, rates.mean(0), color=color, lw=2, label=f"{method}: mean, min-max band, dots = {len(rows)} seeds")
    ax.set_xlabel(f"shift = k x test shift {list(test_xi)}")
    ax.set_ylabel("success rate on the true model")
    ax.set_ylim(-0.03, 1.03)
    ax.set_xticks(list(factors))
    ax.set_title(f"{system_name}: robustness to larger parameter shifts")
    fig.legend(loc="outside lower center", fontsize=8)
    return _save(fig, path)


def against_radius(summary: Sequence[dict], factors: Sequence[float], path: Path, title: str = "") -> Path:
    """A sweep's outcome against the Wasserstein radius r, one line per risk level eps (method ``dr``),
    the baseline (which ignores r) as a dashed level; lines are means over seeds, bands their min-max.

    ``summary`` is :func:`drlyap.workflows.sweep.summarise`'s list; panels: success at the first and last shift
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
