"""``prdp-fem study`` and ``prdp-fem invert``: run a scene's configurations, print the
summary."""

from __future__ import annotations

import dataclasses
import shlex
from pathlib import Path

from ..errors import SceneError
from ._shared import Bars, fresh_directory, interrupt_kept, print_table, scene_for

SUMMARY_COLUMNS = {
    "inverse": ["run", "final_error", "error_gap", "final_K", "time_s", "cg_iterations",
                "reached_step", "time_to_target_s", "time_saving", "iteration_saving",
                "ends_at_or_below"],
    "forward": ["run", "requested_iterations", "iterations", "wall_time_s",
                "relative_l2_error", "relative_energy_error"],
    "h": ["element", "level", "dofs", "l2_error", "rate", "cg_iterations", "cg_setup_time",
          "cg_time", "amg_time"],
    "learned": ["run", "final_error", "validation_misfit", "final_K", "time_s", "cg_iterations",
                "optimizer_steps", "reached_step", "time_to_target_s", "time_saving",
                "iteration_saving"],
    "heat": ["run", "test_error", "validation_error", "final_K", "time_s", "cg_iterations",
             "reached_epoch", "time_saving", "iteration_saving"],
}


def run_study_command(scene, out: Path | None, resume: bool, prefix: str,
                      executor: str = "serial") -> None:
    from ..studies.cluster import executor_client
    from ..studies.runner import RESULTS, SUMMARY, configurations, run_study

    clients = executor_client(executor)  # checked before the output directory is named
    if out is None:
        out = Path(f"{prefix}-{scene.name}") if resume else fresh_directory(
            f"{prefix}-{scene.name}")
    print(f"{scene.name} ({scene.source}): {scene.study.kind} study of "
          f"{len(configurations(scene))} configuration(s) into {out}/", flush=True)
    bars = Bars(len(configurations(scene)))
    continued = shlex.join(["prdp-fem", "study", str(scene.source), "--out", str(out),
                            "--resume"] + (["--executor", executor] if executor != "serial"
                                           else []))
    with interrupt_kept(bars, f"finished records are kept in {out}/{RESULTS} (continue "
                               f"with: {continued})"):
        with clients as client:
            result = run_study(scene, out, resume=resume, progress=bars, client=client)
    bars.close()
    # the table opens with its plain reading: the scene's PRDP run against its reference
    line = headline(scene, result.summary) if scene.study.kind == "inverse" else None
    if line:
        print(line)
    print_table(result.summary, SUMMARY_COLUMNS[scene.study.kind])
    if scene.study.kind == "learned":  # each against the converged run of its optimiser
        alone = [row["run"] for row in result.summary if not row.get("reference")]
        if alone:
            print(f"no saving (no converged run of the same optimiser and batch): "
                  f"{', '.join(alone)}")
    own = [f"{row['run']} against {row['reference']}" for row in result.summary
           if scene.study.kind == "inverse"
           and row.get("reference", scene.study.reference) != scene.study.reference]
    if own:  # the converged run of the same preconditioner
        print(f"savings of runs with their own preconditioner: {'; '.join(own)}")
    figures = ", ".join(str(p.relative_to(out)) for p in result.figures)
    print(f"\nwrote {out}/: {RESULTS}, {SUMMARY}, {figures}"
          + (", fields/*.vtu" if scene.study.kind == "inverse" else ""))


def headline(scene, summary: list[dict]) -> str | None:
    """One plain line on the scene's first PRDP run against its converged reference, by the
    same-target rule of the summary; ``None`` where the scene has no such pair."""
    variants = dict(scene.runs())
    rows = {row["run"]: row for row in summary}
    reference = rows.get(scene.study.reference)
    run = next((name for name, v in variants.items()
                if v.refinement.kind == "prdp" and name in rows), None)
    if reference is None or run is None:
        return None
    row = rows[run]
    if row["reached_step"] == "":
        return (f"PRDP ({run}) did not settle within +-{100 * scene.study.band:g} % of the "
                f"converged run's error (its final error is {100 * row['error_gap']:+.1f} % "
                f"off{', below it' if row['ends_at_or_below'] and row['error_gap'] < 0 else ''}"
                f"): no saving to report")
    return (f"PRDP ({run}) reached the converged run's error in "
            f"{row['time_to_target_s']:.3g} s instead of "
            f"{row['converged_time_to_target_s']:.3g} s "
            f"({100 * row['time_saving']:.0f} % less wall time, "
            f"{100 * row['iteration_saving']:.0f} % fewer CG iterations)")


def study_command(args) -> None:
    run_study_command(scene_for(args.scene, args.steps, args.seed), args.out, args.resume,
                      "study", args.executor)


def invert_command(args) -> None:
    scene = scene_for(args.scene, args.steps)
    if scene.inverse is None:
        raise SceneError(f"{scene.source}: no [inverse] section; expected one to invert")
    study = dataclasses.replace(scene.study, kind="inverse", runs=((scene.name, "{}"),))
    run_study_command(dataclasses.replace(scene, study=study), args.out, False, "invert")
