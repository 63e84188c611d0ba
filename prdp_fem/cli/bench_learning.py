"""``prdp-fem bench learning``: PRDP's saving when training through the solver, over seeds."""

from __future__ import annotations

import shlex

from ._shared import Bars, interrupt_kept, percent, print_table
from .bench import bench_directory, bench_scenes

#: What ``bench learning`` writes beside its scenes' directories (and its bench.json).
LEARNING_TABLE, LEARNING_SEED_TABLE, RANKING_TABLE = "learning.csv", "seeds.csv", "ranking.csv"


def _scenes(args) -> list:
    """The scenes, each a learned or heat scene of a distinct name that can be a directory."""
    from ..bench.learning import LEARNING_SCENES, seeded_scene

    scenes = bench_scenes(args, LEARNING_SCENES,
                          ("bench.json", LEARNING_TABLE, LEARNING_SEED_TABLE, RANKING_TABLE))
    for scene in scenes:
        seeded_scene(scene, args.seeds[0])  # a learned or heat scene, or a one-line error
    return scenes


def _device() -> str:
    """The device the runs train on, as a table's reader needs it: kind and count."""
    import jax

    devices = jax.devices()
    kind = devices[0].device_kind if devices[0].platform != "cpu" else "CPU"
    return f"{len(devices)} x {kind}" if len(devices) > 1 else kind


def _command(args, out) -> str:
    words = ["prdp-fem", "bench", "learning"]
    if args.scene:
        words += ["--scene", *args.scene]
    if args.steps is not None:
        words += ["--steps", str(args.steps)]
    words += ["--seeds", *map(str, args.seeds)]
    if args.executor != "serial":
        words += ["--executor", args.executor]
    return shlex.join([*words, "--out", str(out), "--resume"])


def bench_learning(args) -> None:
    from .._atomic import write_csv_atomic
    from .._lock import directory_lock
    from ..bench.learning import (
        GOAL_ITERATION_SAVING,
        GOAL_TIME_SAVING,
        learning_saving,
        learning_summary,
        rankings,
    )
    from ..studies.cluster import executor_client

    clients = executor_client(args.executor)  # checked before anything runs
    scenes = _scenes(args)
    out = bench_directory(args.out, args.resume, {"scene": args.scene, "steps": args.steps,
                                                  "seeds": args.seeds}, "learning")
    runs = sum(len(scene.runs()) for scene in scenes) * len(args.seeds)
    print(f"learning saving: {len(scenes)} scene(s) x {len(args.seeds)} seed(s), {runs} "
          f"run(s) into {out}/ on {_device()}", flush=True)
    bars, rows = Bars(runs), []
    with directory_lock(out):  # one writer: a second bench on ``out`` fails at once
        with interrupt_kept(bars, f"finished runs and checkpoints are kept in {out}/ "
                                  f"(continue with: {_command(args, out)})"):
            with clients as client:
                for scene in scenes:
                    rows += learning_saving(scene, args.seeds, out / scene.name,
                                            resume=args.resume, progress=bars, client=client)
        bars.close()
        print_table([_row_cells(row) for row in rows], list(_row_cells(rows[0])))
        print()
        summary = learning_summary(rows)
        print_table([_summary_cells(s) for s in summary], list(_summary_cells(summary[0])))
        print()
        orders = rankings(rows)
        print_table([{"scene": r.scene, "seeds": f"{len(r.seeds)}/{r.instances}",
                      "order (lowest test error first)": " < ".join(r.order)}
                     for r in orders], ["scene", "seeds", "order (lowest test error first)"])
        print(f"test_err: held-out test error at the end; gap: test_err / the converged "
              f"partner's (same optimiser and batch, or setup and mode) - 1; band@: the epoch "
              f"from which the test error stays within study.band of the partner's final one; "
              f"save: 1 - time or CG iterations to band@ / the partner's own to its band (not "
              f"its whole run), compilation excluded; ceil: the saving of a run that trains "
              f"every epoch at its first (coarsest) level and reaches the band in as many "
              f"epochs as the partner (1 - its cost per epoch there / the partner's); met: "
              f"save_t >= "
              f"{100 * GOAL_TIME_SAVING:.0f} % and save_its >= "
              f"{100 * GOAL_ITERATION_SAVING:.0f} %; per run over the seeds: medians (ranges) "
              "of the savings over the seeds that reach the band, of the test error over all; "
              "samples/s: training samples (heat: windows) per second of training time")
        write_csv_atomic(out / LEARNING_TABLE,
                         [{**row._asdict(), "met": row.goal_met} for row in rows])
        write_csv_atomic(out / LEARNING_SEED_TABLE, [s._asdict() for s in summary])
        write_csv_atomic(out / RANKING_TABLE,
                         [{"scene": r.scene, "order": " < ".join(r.order),
                           "seeds": " ".join(map(str, r.seeds)), "instances": r.instances}
                          for r in orders])
    if bars.skipped:
        print(f"{bars.skipped} of {runs} run(s) read back from {out}/, as timed in an earlier "
              "process" + ("" if bars.skipped == runs else
                           ": a saving may compare runs timed in different processes"))
    print(f"wrote {out}/: {LEARNING_TABLE}, {LEARNING_SEED_TABLE}, {RANKING_TABLE}, and the "
          f"studies in {', '.join(scene.name + '/seed-*/' for scene in scenes)}")


def _row_cells(row) -> dict:
    partnered = row.converged_run is not None
    return {"scene": row.scene, "seed": row.seed, "run": row.run,
            "test_err": f"{row.test_error:.4g}",
            "gap": percent(row.error_gap, digits=1), "time_s": f"{row.time_s:.4g}",
            "cg_its": row.cg_iterations,
            "band@": "-" if row.reached_epoch is None else row.reached_epoch,
            "save_t": percent(row.time_saving), "save_its": percent(row.iteration_saving),
            "ceil_t": percent(row.time_ceiling), "ceil_its": percent(row.iteration_ceiling),
            "met": ("yes" if row.goal_met else "no") if partnered else "-",
            "samples/s": f"{row.samples_per_s:.4g}"}


def _summary_cells(summary) -> dict:
    partnered = summary.error_gap == summary.error_gap  # NaN: no converged partner
    def spread(median: float, low: float, high: float) -> str:
        if median != median:  # NaN: no seed reached the band
            return "-"
        return f"{percent(median)} ({100 * low:.0f} to {100 * high:.0f} %)"

    return {"scene": summary.scene, "run": summary.run,
            "band": f"{summary.reached}/{summary.instances}" if partnered else "-",
            "met": f"{summary.met}/{summary.instances}" if partnered else "-",
            "save_t": spread(summary.time_saving, summary.time_saving_low,
                             summary.time_saving_high),
            "save_its": spread(summary.iteration_saving, summary.iteration_saving_low,
                               summary.iteration_saving_high),
            "test_err": f"{summary.test_error:.4g} ({summary.test_error_low:.4g} to "
                        f"{summary.test_error_high:.4g})",
            "gap": percent(summary.error_gap, digits=1),
            "ceil_t": percent(summary.time_ceiling),
            "ceil_its": percent(summary.iteration_ceiling),
            "samples/s": f"{summary.samples_per_s:.4g}"}
