"""``prdp-fem evaluate``: test metrics and predictions of a learned or heat study's trained
runs, from their last checkpoints."""

from __future__ import annotations

from pathlib import Path

from ._shared import print_table, scene_for


def evaluate_command(args) -> None:
    from ..studies.evaluation import EVALUATION, evaluate_study

    scene = scene_for(args.scene, args.steps, args.seed)
    out = args.out if args.out is not None else Path(f"study-{scene.name}")
    rows = evaluate_study(scene, out, runs=args.run, samples=args.samples)
    print(f"{scene.name}: test metrics of {len(rows)} run(s) from their last checkpoints in "
          f"{out}/checkpoints/")
    print_table(rows, list(rows[0]))
    what = "sample_*.vtu" if scene.study.kind == "learned" else "rollout_*.pvd"
    print(f"\nwrote {out}/: {EVALUATION}.csv, {EVALUATION}/<run>/metrics.json and {what}")
