"""The states a fit trains on (:class:`TrainingStates`): uniform batches in X_delta, a share near x*, with a
region-of-attraction level states inside the set, and adversarial states moved by projected ascent on the residual
(:func:`ascend`), states on the box's faces moved by projected descent on V (:func:`descend_on_faces`), the faces
where the flow may leave the box (:func:`may_leave`) and states moved by descent among them (:func:`descend_on_exits`);
what the acceptance check adds inside a small set (:func:`inside_states`)."""

from __future__ import annotations

import torch
from torch import Tensor

from drlyap.closed_loop import ClosedLoop
from drlyap.conditions import Condition
from drlyap.networks import Lyapunov
from drlyap.regions import Region
from drlyap.sections import RegionGoal, SamplingSection
from drlyap.systems import UncertainSystem

ADVERSARIAL_STEP = 0.01  # one ascent step of the adversarial states, as a share of the box's width per coordinate
ADVERSARIAL_REFRESH = 0.02  # share of the adversarial states redrawn every iteration
FACE_STATES = 1024  # states on the box's faces drawn anew every iteration, and as many kept and moved by descent
FACE_DESCENT_STATES = 4  # from this many states on: in 2 or 3 the faces are segments or squares that uniform draws cover
EXIT_MARGIN = 0.05  # a face state may be left where the flow's outward part exceeds -this share of the half-width per unit time
EXIT_PENALTY = 20.0  # the exits' descent: V plus this times the shortfall of the flow's outward part (per half-width)


def radial_states(lyapunov: Lyapunov, region: Region, level: float, count: int, generator: torch.Generator) -> Tensor:
    """Up to ``count`` states ``(C, n)`` (float64) of X_delta with ``V <= level``, drawn without rejection: a direction
    uniform on the sphere in box-scaled coordinates, moved out to the set's boundary along its ray (by
    ``sqrt(level / V)``, exact where V is quadratic) and then back in by a uniform share ``U^(1/n)``. In 6 states a
    sublevel set of 1e-3 of the box holds about 4 of 4,096 uniform draws; these states spread over all of it (uniform
    draws in the box, moved in the same way, would crowd the box's diagonals)."""
    direction = torch.randn(count, region.n, generator=generator, dtype=region.lo.dtype)
    z = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-30) * region.hi.maximum(-region.lo)
    z = z * (_to_boundary(lyapunov, z, level) * torch.rand(count, generator=generator, dtype=z.dtype)
             ** (1.0 / region.n))[:, None]
    with torch.no_grad():
        keep = region.contains(z) & (lyapunov(z.to(next(lyapunov.parameters()))).double().cpu() <= level)
    return z[keep]


def _to_boundary(lyapunov: Lyapunov, z: Tensor, level: float) -> Tensor:
    """``(B,)`` float64: the factor ``sqrt(level / V(z))`` that moves each state of ``z (B, n)`` (float64, CPU) along
    its ray from x* onto ``{V = level}`` (exactly where V is quadratic)."""
    with torch.no_grad():
        value = lyapunov(z.to(next(lyapunov.parameters()))).double().cpu()
    return torch.sqrt(level / value.clamp_min(1e-30))


def adversarial_starts(lyapunov: Lyapunov, region: Region, level: float | None, count: int,
                       generator: torch.Generator) -> Tensor:
    """``(count, n)`` float64 starts of adversarial states: :func:`radial_states` in ``{V <= level}``, topped up with
    uniform states of X_delta (all uniform without a level)."""
    if level is None:
        return region.sample(count, generator)
    z = radial_states(lyapunov, region, level, 2 * count, generator)[:count]
    return torch.cat([z, region.sample(count - z.shape[0], generator)]) if z.shape[0] < count else z


def ascend(loop: ClosedLoop, condition: Condition, z: Tensor, region: Region, level: float | None) -> Tensor:
    """One step of projected ascent on the residual from states ``z (B, n)`` (float32 or the networks' dtype):
    ``ADVERSARIAL_STEP`` of the box's width along the width-scaled, normalised gradient, then back into X_delta and,
    with a level, onto ``{V <= level}`` by moving towards x* (exact for a quadratic V). No gradient reaches the
    weights."""
    with torch.enable_grad():
        x = z.detach().requires_grad_(True)
        grad = torch.autograd.grad(condition.residual(condition.terms(loop, x)).sum(), x)[0]
    moved = region.ascent_step(z.detach(), grad, ADVERSARIAL_STEP)
    if level is not None:
        moved = region.project(moved * _to_boundary(loop.lyapunov, moved, level).clamp(max=1.0)[:, None])
    return moved.to(z)


def descend_on_faces(lyapunov: Lyapunov, z: Tensor, region: Region) -> Tensor:
    """One step of projected descent on V from states ``z (B, n)`` on the box's faces, within their faces: the
    coordinates at a bound of the box stay there, the others move ``ADVERSARIAL_STEP`` of the box's width along the
    width-scaled, normalised gradient. A tilted sublevel set meets a face of a 6-state box in a patch that uniform
    draws on the faces miss; these states find it. No gradient reaches the weights."""
    with torch.enable_grad():
        x = z.detach().requires_grad_(True)
        grad = torch.autograd.grad(lyapunov(x).sum(), x)[0]
    on_face = (z == region.lo.to(z)) | (z == region.hi.to(z))
    return region.ascent_step(z.detach(), -grad.masked_fill(on_face, 0.0), ADVERSARIAL_STEP).to(z)


def inside_states(lyapunov: Lyapunov, region: Region, level: float, count: int, device: torch.device,
                  generator: torch.Generator, tries: int = 20) -> Tensor:
    """Up to ``count`` states ``(C, n)`` of X_delta with ``V <= level``: uniform draws kept by rejection, at most
    ``tries`` rounds of ``4 count`` draws; float32 on ``device``."""
    kept = []
    found = 0
    with torch.no_grad():
        for _ in range(tries):
            z = region.sample(4 * count, generator).float().to(device)
            z = z[lyapunov(z) <= level]
            kept.append(z)
            found += z.shape[0]
            if found >= count:
                break
    return torch.cat(kept)[:count]


def exit_speed(loop: ClosedLoop, xi: Tensor, z: Tensor, region: Region) -> Tensor:
    """``(F,)``: how fast the design model's flow at the samples ``xi (N, k)`` may leave the box at the states
    ``z (F, n)`` on its faces, the largest outward component through a face a state lies on, over the samples, in
    shares of the box's half-width per unit time (below 0 where every sample's flow enters the box). Differentiable
    in ``z``."""
    f, w = loop.system.design_model(loop.system.to_user(z), loop.controller(z))
    zdot = f + torch.einsum("bnk,jk->jbn", w, xi.to(f))  # (N, F, n)
    lo, hi = region.lo.to(z), region.hi.to(z)
    outward = torch.where(z >= hi, zdot, torch.where(z <= lo, -zdot, torch.full_like(zdot, -torch.inf)))
    return (outward / ((hi - lo) / 2)).amax(-1).amax(0)


def may_leave(loop: ClosedLoop, xi: Tensor, z: Tensor, region: Region) -> Tensor:
    """``(F,)`` bool: the states ``z (F, n)`` on the box's faces where the design model's flow at some sample of
    ``xi (N, k)`` may leave the box: its component out through a face the state lies on is above ``-EXIT_MARGIN``
    of the box's half-width per unit time (the margin takes in the points a shift may turn outwards). No gradient."""
    with torch.no_grad():
        return exit_speed(loop, xi, z, region) > -EXIT_MARGIN


def descend_on_exits(loop: ClosedLoop, xi: Tensor, z: Tensor, region: Region) -> Tensor:
    """One step of :func:`descend_on_faces` on V plus ``EXIT_PENALTY`` times how far a state falls short of
    :func:`may_leave` (:func:`exit_speed` below ``-EXIT_MARGIN``): the states gather where V is least among the face
    points the flow may leave, which uniform draws on the faces miss (there the verifier's level search at a shift
    stops). No gradient reaches the weights."""
    with torch.enable_grad():
        x = z.detach().requires_grad_(True)
        short = torch.relu(-EXIT_MARGIN - exit_speed(loop, xi, x, region))
        grad = torch.autograd.grad((loop.lyapunov(x) + EXIT_PENALTY * short).sum(), x)[0]
    on_face = (z == region.lo.to(z)) | (z == region.hi.to(z))
    return region.ascent_step(z.detach(), -grad.masked_fill(on_face, 0.0), ADVERSARIAL_STEP).to(z)


class TrainingStates:
    """The states a fit trains on, drawn from ``gen`` (in this order: a batch, then the adversarial states, at the start;
    then each iteration a new batch where ``sampling.resample``, a share of the adversarial states redrawn and all of
    them moved one ascent step, and the faces' states of a level's term): uniform in X_delta (the section's training
    box minus the ball, where it has one), a share near x*, with the goal's level up to half of the uniform share inside
    ``{V <= 1.25 level}``, adversarial states, and the ``extra`` states (E, n) in every batch. Float32 on
    ``device``; ``region`` is X_delta, whose faces bound the set."""

    def __init__(self, sampling: SamplingSection, goal: RegionGoal, system: UncertainSystem, region: Region,
                 lyapunov: Lyapunov, gen: torch.Generator, device: torch.device, extra: Tensor | None) -> None:
        self.sampling, self.system, self.region, self.lyapunov = sampling, system, region, lyapunov
        self.gen, self.device, self.extra = gen, device, extra
        self.n_states, self.resample = int(sampling.n_states), bool(sampling.resample)
        self.n_near, self.n_adv = sampling.counts()
        self.refresh = max(1, int(ADVERSARIAL_REFRESH * self.n_adv))
        self.level = goal.level  # the claimed level, or above it by the level margin
        self.faces_level = goal.faces_level
        self.entry_level = goal.entry_faces_level  # below faces_level with exit_faces: where the flow enters the box
        self.entry_check = goal.entry_level  # what the acceptance check asks where the flow enters the box
        self.drawn_in = region
        self.faces = None  # fixed states on the box's faces for the acceptance check (own generator)
        self.face_minima: Tensor | None = None  # face states moved by descent on V (with a level)
        self.face_gen: torch.Generator | None = None
        self.exits = goal.exit_faces_level is not None  # exit_faces with a level: kept states among the exits
        self.exit_level = goal.exit_faces_level if self.exits else self.faces_level  # where the flow may leave the box
        self.exit_minima: Tensor | None = None  # face states moved by descent on V among the exits (exit_faces)
        self.exit_gen: torch.Generator | None = None
        self.batch: Tensor | None = None
        self.adversaries: Tensor | None = None

    def start(self) -> None:
        """The region states are drawn in, the faces' states of the acceptance check, the first batch and the
        adversarial states."""
        self.drawn_in = self.sampling.sampling_region(self.system)
        if self.level is not None:
            self.faces = self.region.sample_faces(20000, torch.Generator().manual_seed(12345)).float().to(self.device)
        if self.level is not None and self.region.n >= FACE_DESCENT_STATES:
            # their own generator: where V stays above the faces' level they add nothing, and training is what it was
            self.face_gen = torch.Generator().manual_seed(54321)
            self.face_minima = self.region.sample_faces(FACE_STATES, self.face_gen).float().to(self.device)
            if self.exits:
                self.exit_gen = torch.Generator().manual_seed(67890)
                self.exit_minima = self.region.sample_faces(FACE_STATES, self.exit_gen).float().to(self.device)
        self.batch = self.draw()
        if self.n_adv:
            self.adversaries = adversarial_starts(self.lyapunov, self.drawn_in, self.level, self.n_adv,
                                                  self.gen).float().to(self.device)

    def draw(self) -> Tensor:
        """A new batch ``(B, n)``: uniform (with a level, up to half of it inside the set), near x*, and the extra ones."""
        n_uniform = self.n_states - self.n_near - self.n_adv
        z = self.drawn_in.sample(n_uniform, self.gen)
        if self.level is not None:  # up to half of the uniform share from inside (or just outside) the sublevel set
            inside = inside_states(self.lyapunov, self.drawn_in, 1.25 * self.level, n_uniform // 2, self.device,
                                   self.gen, tries=1)
            z = torch.cat([inside.double().cpu(), z[: n_uniform - inside.shape[0]]])
        if self.n_near:
            z = torch.cat([z, self.drawn_in.sample_near(self.n_near, self.gen)])
        z = z.float().to(self.device)
        return z if self.extra is None else torch.cat([z, self.extra])

    def next(self, iteration: int, loop: ClosedLoop, condition: Condition) -> Tensor:
        """The states of ``iteration`` (from 1): the batch (new where the section resamples) and the adversarial states,
        a share of them redrawn and all moved one ascent step on the residual."""
        if self.resample and iteration > 1:
            self.batch = self.draw()
        if self.adversaries is None:
            return self.batch
        row = (iteration * self.refresh) % self.n_adv
        fresh = adversarial_starts(self.lyapunov, self.drawn_in, self.level, self.refresh, self.gen)
        self.adversaries[row:row + self.refresh] = fresh[: self.n_adv - row].float().to(self.device)
        self.adversaries = ascend(loop, condition, self.adversaries, self.drawn_in, self.level)
        return torch.cat([self.batch, self.adversaries])

    def face_levels(self, loop: ClosedLoop, xi: Tensor, z: Tensor, level: float, entry: float,
                    dtype: torch.dtype | None = None) -> Tensor:
        """``(F,)`` in ``dtype`` (default: ``z``'s): the level V is asked above at each state of ``z (F, n)`` on the
        faces, ``level`` where the flow may leave the box (:func:`may_leave` at the samples ``xi (N, k)``) and
        ``entry`` elsewhere; ``level`` everywhere where the two are equal (without ``exit_faces``)."""
        dtype = dtype or z.dtype
        if entry == level:
            return torch.full((z.shape[0],), float(level), dtype=dtype, device=z.device)
        leave = may_leave(loop, xi, z, self.region)
        at = {"dtype": dtype, "device": z.device}
        return torch.where(leave, torch.tensor(float(level), **at), torch.tensor(float(entry), **at))

    def faces_term(self, loop: ClosedLoop, xi: Tensor, iteration: int) -> Tensor:
        """The mean shortfall of V below the faces' level (:meth:`face_levels`) at ``FACE_STATES`` new states of the
        box's faces; from ``FACE_DESCENT_STATES`` states on, plus the mean shortfall of those kept face states that
        fall short, a share of them redrawn and all moved one descent step on V (:func:`descend_on_faces`): they
        gather where V is least on each face, and only the faces the set crosses count (averaged over all of them, a
        set crossing one face of twelve would barely feel it). With ``exit_faces``, as many kept states again move
        by descent among the points the flow may leave (:func:`descend_on_exits`), V asked above the exits' level
        there. ``xi (N, k)``: the condition's samples."""
        lyapunov = loop.lyapunov
        faces = self.region.sample_faces(FACE_STATES, self.gen).float().to(self.device)
        levels = self.face_levels(loop, xi, faces, self.exit_level, self.entry_level)
        uniform = torch.relu(levels - lyapunov(faces)).mean()
        if self.face_minima is None:
            return uniform
        self.face_minima = self._refresh(self.face_minima, self.face_gen, iteration)
        self.face_minima = descend_on_faces(lyapunov, self.face_minima, self.region)
        levels = self.face_levels(loop, xi, self.face_minima, self.exit_level, self.entry_level)
        term = uniform + _mean_short(levels - lyapunov(self.face_minima))
        if self.exit_minima is None:
            return term
        self.exit_minima = self._refresh(self.exit_minima, self.exit_gen, iteration)
        self.exit_minima = descend_on_exits(loop, xi, self.exit_minima, self.region)
        leave = may_leave(loop, xi, self.exit_minima, self.region)
        return term + _mean_short((self.exit_level - lyapunov(self.exit_minima))[leave])

    def _refresh(self, kept: Tensor, gen: torch.Generator, iteration: int) -> Tensor:
        """``kept (FACE_STATES, n)`` with the share ``ADVERSARIAL_REFRESH`` of its rows that ``iteration`` turns to
        redrawn on the faces from ``gen``."""
        refresh = max(1, int(ADVERSARIAL_REFRESH * FACE_STATES))
        row = (iteration * refresh) % FACE_STATES
        fresh = self.region.sample_faces(refresh, gen).float().to(self.device)
        kept[row:row + refresh] = fresh[:FACE_STATES - row]
        return kept

    def check_faces(self, loop: ClosedLoop, xi: Tensor) -> tuple[Tensor, Tensor] | None:
        """The acceptance check's face states ``(F, n)``, the fixed uniform ones and the kept descended ones (on V, and
        with ``exit_faces`` among the exits), and the level ``(F,)`` V must exceed at each: the training level, or with
        ``exit_faces`` the claimed one where the flow enters the box. None without a level."""
        if self.faces is None:
            return None
        kept = [t for t in (self.face_minima, self.exit_minima) if t is not None]
        faces = torch.cat([self.faces, *kept])
        return faces, self.face_levels(loop, xi, faces, self.level, self.entry_check, torch.float64)


def _mean_short(short: Tensor) -> Tensor:
    """The mean of the positive entries of ``short (F,)`` (0 where none is): a shortfall of V below a level."""
    short = torch.relu(short)
    return short.sum() / (short > 0).sum().clamp_min(1)
