"""How far the verifier's bound is from the truth on the boxes a proof had to split (trains and proves nothing).

Usage::

    python benchmarks/gap_bench.py RUN_DIR [RUN_DIR ...] [--boxes 1000] [--samples 512] [--seed 0] [--threads 1]

A proof splits a box when the upper bound of the residual over it is above 0. For a run's certificate of its trained
condition (``certificates/trained.*``, written by ``drlyap train`` or ``drlyap verify``), this takes ``--boxes``
random *parents of two proved leaves*: boxes the proof split once and then proved in both halves, and bounds them
again with the run's enclosure. It prints, per run:

* the share of those parents whose bound is now <= 0 (the proof would not have split them; 0 with the bound that
  made the certificate);
* the sampled maximum of the residual over each parent (``--samples`` uniform states, those with ``V <= level`` on a
  sublevel set): below 0 means that the condition holds there as far as sampling sees, so the split was the bound's
  doing, not the condition's;
* the gap between the bound and that maximum, as a multiple of the margin ``|max|``, and the share of the parents a
  bound with half the gap would have proved: what a tighter bound would save, before it is written;
* with affine forms, where the gap comes from: the remainder of the residual's components (the interval of the form
  above its quadratic part: every nonlinear step's and product's terms of third order and above, and rounding) as a
  multiple of the margin, and the gap between the form's polynomial part (its constant, linear and quadratic parts,
  no remainder) at the same states and the sampled maximum, in margins: a remainder near the gap and a polynomial near the
  residual say that the quadratic model is accurate and its remainder's enclosure is what splits the box.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

F64 = torch.float64


def parents_of_proved_pairs(arrays: dict) -> torch.Tensor:
    """Indices of the partition's nodes split once whose two halves are proved leaves."""
    from drlyap.verification.partition import INTERNAL, PROVED

    parent = torch.as_tensor(arrays["parent"].astype(np.int64))
    verdict = torch.as_tensor(arrays["verdict"].astype(np.int64))
    has = parent >= 0
    children = torch.zeros_like(parent).index_add_(0, parent[has], torch.ones_like(parent[has]))
    proved = torch.zeros_like(parent).index_add_(0, parent[has], (verdict[has] == PROVED).long())
    return ((verdict == INTERNAL) & (children == 2) & (proved == 2)).nonzero().squeeze(-1)


def sampled_max(loop, condition, level: float | None, lo: torch.Tensor, hi: torch.Tensor,
                t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B,)``: the largest residual at the states ``lo + (hi - lo) t`` of each box (``t (M, B, n)`` in ``[0, 1]``;
    ``-inf`` where none has V <= level), and which of those states count ``(M, B)`` (V <= level)."""
    flat = (lo + (hi - lo) * t).reshape(-1, lo.shape[1])
    values = loop.exact(condition, flat).reshape(t.shape[:2])
    inside = torch.ones_like(values, dtype=torch.bool)
    if level is not None:
        with torch.no_grad():
            inside = loop.lyapunov(flat).reshape(t.shape[:2]) <= level
    return torch.where(inside, values, -torch.inf).amax(0), inside


def remainder_split(loop, condition, lo: torch.Tensor, hi: torch.Tensor, t: torch.Tensor,
                    inside: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B,)`` each: the largest remainder (upper end) over the residual's components' affine forms over the boxes, and
    the largest value of the residual combined from the forms' polynomial parts at the states ``lo + (hi - lo) t`` that
    count (``inside``, from :func:`sampled_max`; ``-inf`` where none)."""
    from drlyap.enclosures import Affine
    from drlyap.verification.bounds import condition_and_value_objective

    form = condition_and_value_objective(loop, condition)(Affine.box(lo, hi))
    e = 2 * t - 1  # the states' noise symbols
    poly = form.c + torch.einsum("bqk,mbk->mbq", form.g, e) + torch.einsum("bqkl,mbk,mbl->mbq", form.q, e, e)
    modelled = torch.where(inside, condition.combine(poly[..., :-1]), -torch.inf).amax(0)
    return form.r.hi[:, :-1].amax(-1), modelled


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run directories with a certificate of their trained condition")
    parser.add_argument("--boxes", type=int, default=1000, help="parents drawn per run [1000]")
    parser.add_argument("--samples", type=int, default=512, help="uniform states per parent [512]")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads [1]")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from drlyap.checker.check import rebuild_boxes
    from drlyap.kinds import Enclosure
    from drlyap.runs import load_run
    from drlyap.runs.certificates import read_certificate
    from drlyap.verification.bounding import ConditionJob

    header = (f"{'run':<24} {'parents':>9} {'drawn':>6} {'bound<=0':>9} {'sampled<0':>10} {'gap/|max| p50':>14} "
              f"{'p90':>6} {'proved at half the gap':>23} {'remainder/|max|':>16} {'polynomial-max':>15}")
    print(header)
    print("-" * len(header))
    for path in args.runs:
        run = load_run(path)
        head, arrays = read_certificate(run.path, "trained")
        region = head["claim"]["region"]
        lo, hi = (torch.as_tensor(region[k], dtype=F64) for k in ("box_lo", "box_hi"))
        level = region.get("level")
        blo, bhi = rebuild_boxes(lo, hi, head["partition"]["grid"], arrays)
        candidates = parents_of_proved_pairs(arrays)
        g = torch.Generator().manual_seed(args.seed)
        pick = candidates[torch.randperm(candidates.numel(), generator=g)[:args.boxes]]
        enclosure = head["partition"].get("enclosure") or (run.proof.enclosure if run.proof else None)
        job = ConditionJob(run.loop.f64, run.condition, level, enclosure)
        upper = job(blo[pick], bhi[pick])["upper"]
        t = torch.rand(args.samples, *blo[pick].shape, generator=g, dtype=F64)
        best, inside = sampled_max(run.loop.f64, run.condition, level, blo[pick], bhi[pick], t)
        seen = torch.isfinite(best)
        gap = (upper - best)[seen] / best[seen].abs().clamp(min=1e-12)
        half = (best + 0.5 * (upper - best))[seen] <= 0
        print(f"{str(path)[-24:]:<24} {candidates.numel():>9,} {pick.numel():>6} "
              f"{float((upper <= 0).double().mean()):>9.3f} {float((best[seen] < 0).double().mean()):>10.3f} "
              f"{float(gap.median()):>14.2f} {float(gap.quantile(0.9)):>6.2f} {float(half.double().mean()):>23.3f}",
              end="")
        if enclosure != Enclosure.AFFINE:
            print(f" {'-':>16} {'-':>15}")
            continue
        rem, modelled = remainder_split(run.loop.f64, run.condition, blo[pick], bhi[pick], t, inside)
        margin = best[seen].abs().clamp(min=1e-12)
        print(f" {float((rem[seen] / margin).median()):>16.2f} "
              f"{float(((modelled - best)[seen] / margin).median()):>15.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
