"""``prdp-fem bench ...``: the benchmarks (cg, memory, amg, mother, prdp, descent, batch,
scale, learning)."""

from __future__ import annotations

import itertools
import json
import math
import shlex
from pathlib import Path

from ..errors import SolverConfigError
from ._shared import (
    Bars,
    as_option,
    fresh_directory,
    interrupt_kept,
    percent,
    percent_range,
    print_table,
    scene_for,
)

#: The files of a ``bench prdp`` output directory, beside its scenes' own directories.
BENCH_MANIFEST, SAVING_TABLE, SEED_TABLE = "bench.json", "saving.csv", "seeds.csv"
DEFAULT_INNER_K = 5  # prdp_fem.bench.inverse.DEFAULT_K (not imported here: jax loads slowly)


def _bench_cg(args) -> None:
    from ..bench.cg import cg_iteration_cost, scaling_slope

    sides = args.sides or ([128, 256, 512, 1024] if args.dim == 2 else [32, 48, 64, 80])
    for option, values, minimum in (("--sides", sides, 2), ("--iterations",
                                    [args.iterations], 1), ("--repeats", [args.repeats], 1)):
        if any(v < minimum for v in values):
            shown = " ".join(map(str, values))
            raise SolverConfigError(f"{option} {shown}: expected integers >= {minimum}")
    import jax

    if args.reference == "device" or (args.reference == "auto"
                                      and jax.default_backend() != "cpu"):
        return _bench_cg_device(args, sides)
    print(f"P1 Laplacian, {args.dim}-D; Jacobi-PCG iteration inside the jitted loop / one SciPy "
          f"CSR SpMV (median of {args.repeats} interleaved repeats); PCG: as the package "
          "compiles it, XLA: XLA's own fusion emitters forced, COO: the segment-sum kernel")
    print(f"{'dofs':>9} {'nnz':>9} {'SpMV [ms]':>10} {'PCG it [ms]':>12} {'ratio':>7} "
          f"{'XLA it [ms]':>12} {'XLA ratio':>10} {'COO it [ms]':>12} {'COO ratio':>10} "
          f"{'compile [s]':>12}")
    costs = []
    for side in sides:
        cost = cg_iteration_cost(side, dim=args.dim, iterations=args.iterations,
                                 repeats=args.repeats)
        costs.append(cost)
        print(f"{cost.n_dofs:>9} {cost.nnz:>9} {1e3 * cost.spmv_s:>10.3f} "
              f"{1e3 * cost.iteration_s:>12.3f} {cost.ratio:>7.2f} "
              f"{1e3 * cost.xla_iteration_s:>12.3f} {cost.xla_ratio:>10.2f} "
              f"{1e3 * cost.coo_iteration_s:>12.3f} {cost.coo_ratio:>10.2f} "
              f"{cost.compile_s:>12.2f}", flush=True)
    if len({c.n_dofs for c in costs}) > 1:
        print(f"log-log slope of the PCG iteration time against dofs: "
              f"{scaling_slope(costs):.2f}")


def _bench_cg_device(args, sides: list[int]) -> None:
    import jax

    from ..bench.cg import device_iteration_cost, scaling_slope
    from ..linalg.operator import KERNELS, default_kernel

    device = jax.devices()[0].device_kind
    print(f"P1 Laplacian, {args.dim}-D, on {device}; Jacobi-PCG iteration inside the jitted "
          f"loop per kernel / one device CSR SpMV (median of {args.repeats} interleaved "
          f"repeats); default kernel: {default_kernel()}")
    print(f"{'dofs':>9} {'nnz':>9} {'SpMV [us]':>10} "
          + " ".join(f"{name + ' it [us]':>12}" for name in KERNELS)
          + f" {'ratio':>7} {'compile [s]':>12}")
    costs = []
    for side in sides:
        cost = device_iteration_cost(side, dim=args.dim, iterations=args.iterations,
                                     repeats=args.repeats)
        costs.append(cost)
        print(f"{cost.n_dofs:>9} {cost.nnz:>9} {1e6 * cost.spmv_s:>10.1f} "
              + " ".join(f"{1e6 * cost.kernel_s[name]:>12.1f}" for name in KERNELS)
              + f" {cost.ratio:>7.2f} {cost.compile_s:>12.2f}", flush=True)
    if len({c.n_dofs for c in costs}) > 1:
        print(f"log-log slope of the PCG iteration time against dofs: "
              f"{scaling_slope(costs):.2f}")


def _bench_memory(args) -> None:
    from ..bench.memory import ALLOCATORS, memory_cost

    columns = ["mode", "K", "segment", "allocator", "peak MB", "n-vectors", "XLA temp MB",
               "grad [s]", "faults/call", "ratio"]
    widths = [12, 6, 8, 9, 9, 10, 12, 9, 11, 6]
    allocators = ALLOCATORS if args.allocator == "both" else (args.allocator,)
    header_printed = False
    default_time = {}  # (mode, K) -> the default allocator's time, for the reuse row's ratio

    def ratio(row) -> str:
        if row.allocator == "default":
            default_time[row.mode, row.iterations] = row.gradient_s
            return "-"
        base = default_time.get((row.mode, row.iterations))
        if base is None or math.isnan(base) or not row.ran:  # no pair, or one side skipped
            return "-"
        return f"{row.gradient_s / base:.2f}"

    def emit(row):
        nonlocal header_printed
        if not header_printed:
            print(f"P1 Poisson on unit_square({args.side}): {row.n_dofs} dofs, one n-vector = "
                  f"{row.vector_mb:.3g} MB\npeak: resident memory of one jitted gradient above "
                  "its own process's baseline (problem built, gradient compiled)"
                  + ("" if row.hwm_reset else " [high-water mark not reset: small peaks read 0]"))
            print("  ".join(c.rjust(w) for c, w in zip(columns, widths, strict=True)))
            header_printed = True
        cells = [row.mode, str(row.iterations), "-" if row.segment is None else str(row.segment),
                 row.allocator, f"{row.peak_mb:.1f}" if row.ran else "skipped",
                 f"{row.peak_mb / row.vector_mb:.1f}" if row.ran else "-",
                 f"{row.xla_temp_mb:.1f}", f"{row.gradient_s:.3g}" if row.ran else "-",
                 "-" if math.isnan(row.faults_per_call) else f"{row.faults_per_call:.0f}",
                 ratio(row)]
        print("  ".join(c.rjust(w) for c, w in zip(cells, widths, strict=True)), flush=True)

    try:
        memory_cost(args.side, tuple(args.iterations), modes=tuple(args.modes),
                    segment=args.segment, repeats=args.repeats, max_mb=args.max_mb,
                    allocators=allocators, on_row=emit)
    except SolverConfigError as error:  # name the command-line option, not the keyword
        raise SolverConfigError(as_option(str(error))) from None


def _bench_amg(args) -> None:
    from ..bench.amg import amg_cost
    from ..linalg.amg import IMPLEMENTATIONS

    for option, values, minimum in (("--sides", args.sides, 2),
                                    ("--cube-sides", args.cube_sides, 2),
                                    ("--repeats", [args.repeats], 1)):
        if any(v < minimum for v in values):
            shown = " ".join(map(str, values))
            raise SolverConfigError(f"{option} {shown}: expected integers >= {minimum}")
    if not args.sides and not args.cube_sides:
        raise SolverConfigError("--sides, --cube-sides: both empty; expected a problem size")
    unknown = [i for i in args.implementations if i not in IMPLEMENTATIONS]
    if unknown:
        raise SolverConfigError(f"--implementations {' '.join(args.implementations)}: "
                                f"expected some of {' '.join(IMPLEMENTATIONS)}")
    print(f"P1 Poisson to rtol 1e-10; ours: jitted ConvergedCG + AMG, pyamg: "
          f"ml.solve(accel='cg') on the same hierarchy; median of {args.repeats} pairs")
    print(f"{'dim':>3} {'dofs':>8} {'impl':>8} {'its':>4} {'pyamg':>5} {'equal':>5} "
          f"{'setup [s]':>9} {'pyamg':>6} {'ratio':>5} {'solve [s]':>9} {'pyamg':>6} "
          f"{'ratio':>5} {'compile [s]':>11}")
    problems = [(side, 2) for side in args.sides] + [(side, 3) for side in args.cube_sides]
    for side, dim in problems:
        for c in amg_cost(side, dim=dim, implementations=tuple(args.implementations),
                          repeats=args.repeats):
            print(f"{c.dim:>3} {c.n_dofs:>8} {c.implementation:>8} {c.iterations:>4} "
                  f"{c.pyamg_iterations:>5} {'yes' if c.iterations_equal else 'no':>5} "
                  f"{c.setup_s:>9.3f} {c.pyamg_setup_s:>6.3f} {c.setup_ratio:>5.2f} "
                  f"{c.solve_s:>9.3f} {c.pyamg_solve_s:>6.3f} {c.ratio:>5.2f} "
                  f"{c.compile_s:>11.2f}", flush=True)


def _bench_batch(args) -> None:
    from ..bench.batch import batch_throughput

    print(f"batched inversion: {args.steps} L-BFGS steps per problem, PRDP per member, noise "
          f"seeds of the mother-type source problem on a {args.n} x {args.n} mesh; one "
          "invert_batch call (vmap: members together, map: in turn) against a loop of invert "
          f"calls, alternated, medians of {args.repeats}")
    print(f"{'members':>7} {'mode':>4} {'dofs':>6} {'batch [s]':>9} {'loop [s]':>9} "
          f"{'batch /s':>9} {'loop /s':>8} {'speedup':>7} {'compile [s]':>11} {'max K':>5} "
          f"{'max diff':>9}")
    for row in batch_throughput(args.sizes, n=args.n, steps=args.steps, repeats=args.repeats):
        print(f"{row.members:>7} {row.mode:>4} {row.dofs:>6} {row.batch_s:>9.3f} "
              f"{row.loop_s:>9.3f} {row.batch_rate:>9.2f} {row.loop_rate:>8.2f} "
              f"{row.speedup:>7.2f} {row.compile_s:>11.2f} {row.largest_K:>5} "
              f"{row.max_difference:>9.1e}", flush=True)
    print("batch /s, loop /s: problems per second; speedup: median of the per-repeat ratios "
          "loop / batch; compile: the batched program's (the loop's step is compiled once for "
          "all sizes); max diff: the largest relative difference of a member's result from its "
          "single run's (vmap sums its reductions in another order; map is the loop's "
          "arithmetic)")


def _percent(value: float) -> str:
    return "nan" if value != value else f"{value:.0%}"


def _bench_scale(args) -> None:
    from ..bench.scale import inversion_at_scale, parse_mesh, sharded_iteration

    for spec in args.meshes:  # all checked before the first one runs
        parse_mesh(spec)
    if args.meshes:
        print(f"log-kappa inversion, P1, AMG-PCG, {args.steps} L-BFGS steps: converged "
              "(rtol 1e-10) against PRDP (K0 = 4, dK = 2); a fresh process per mesh")
        print(f"{'mesh':>12} {'dofs':>8} {'setup [s]':>9} {'conv/step':>9} {'prdp/step':>9} "
              f"{'conv->t [s]':>11} {'@step':>5} {'prdp->t [s]':>11} {'save t':>6} "
              f"{'save its':>8} {'prdp<=t [s]':>11} {'save t':>6} {'conv err':>8} "
              f"{'prdp err':>8} {'K':>3} {'compile':>7} {'peak RSS':>8}")
        for spec in args.meshes:
            (r,) = inversion_at_scale([spec], steps=args.steps)
            print(f"{r.mesh:>12} {r.dofs:>8} {r.setup_s:>9.1f} {r.converged_step_s:>9.3f} "
                  f"{r.prdp_step_s:>9.3f} {r.converged_to_target_s:>11.1f} "
                  f"{r.converged_reached_step:>5} {r.prdp_to_target_s:>11.1f} "
                  f"{_percent(r.time_saving):>6} {_percent(r.iteration_saving):>8} "
                  f"{r.prdp_at_or_below_s:>11.1f} {_percent(r.at_or_below_saving):>6} "
                  f"{r.converged_error:>8.4f} {r.prdp_error:>8.4f} {r.final_K:>3} "
                  f"{r.compile_s:>7.1f} {r.peak_rss_gb:>6.2f} GB", flush=True)
        print("per step: run time without compilation / steps; conv->t: the converged run's "
              "own time to its final error (from the step @step on it stays within 1 %); "
              "prdp->t: PRDP's time to stay within that band, prdp<=t: to stay at or below "
              "its top; save: 1 - PRDP's / the converged run's, t: time, its: CG iterations "
              "(nan: not reached); peak RSS: the process's high-water mark")
    if args.sharded_n:
        print(f"\nJacobi-PCG, {args.iterations} iterations per solve, 2-D P1 on "
              f"unit_square({args.sharded_n}); forced host devices sharing this machine's "
              f"cores; alternated, medians of {args.repeats}")
        print(f"{'devices':>7} {'dofs':>8} {'halo':>6} {'per iteration [ms]':>18} "
              f"{'vs one device':>13}")
        for r in sharded_iteration(args.sharded_n, tuple(args.devices), args.iterations,
                                   args.repeats):
            name = "one" if r.devices == 0 else str(r.devices)
            print(f"{name:>7} {r.dofs:>8} {r.halo:>6} {r.iteration_ms:>18.3f} "
                  f"{r.ratio:>13.2f}", flush=True)
        print("one: the plain kernel on one device; 1, 2, 4: spread over a jax.sharding.Mesh "
              "of that many devices (halo: values a device receives per product)")


def _bench_mother(args) -> None:
    from ..bench.inverse import (
        CACHES,
        PEER_INSTALL,
        RACE_INNER_RTOL,
        check_mother_options,
        mother_optimum,
        mother_whole_process,
    )

    caches = CACHES if args.cache == "both" else (args.cache,)  # argparse checked the name
    if args.iterations is not None and args.inner_rtol is not None:
        raise SolverConfigError("--iterations and --inner-rtol: expected one of them (PRDP "
                                "on the inner solves, or converged inner solves)")
    inner_options = {"--iterations": args.iterations, "--inner-rtol": args.inner_rtol,
                     "--preconditioner": args.preconditioner}
    given = [name for name, value in inner_options.items() if value is not None]
    if args.solver == "kkt" and given:
        raise SolverConfigError(f"{' '.join(given)}: options of the inner solves of "
                                "--solver reduced; expected none with --solver kkt")
    preconditioner = args.preconditioner or "amg"
    K = DEFAULT_INNER_K if args.iterations is None else args.iterations
    inner_rtol = None if args.iterations is not None else (
        RACE_INNER_RTOL if args.inner_rtol is None else args.inner_rtol)
    check_mother_options(args.sizes, repeats=args.repeats, target=args.target, K=K,
                         inner_rtol=inner_rtol, preconditioner=preconditioner,
                         solver=args.solver)
    if args.solver == "kkt":
        print("all-at-once MINRES on the KKT system, Pearson-Wathen preconditioner (AMG "
              "V-cycles of A + M / sqrt(alpha))")
    else:
        inner = f"PRDP K0 = dK = {K}" if inner_rtol is None else f"rtol {inner_rtol:g}"
        print(f"reduced-Hessian CG, inner {preconditioner}-PCG: {inner}")
    if args.peer_python is None:
        print(f"no peer given: the project's side alone (to race dolfin-adjoint: {PEER_INSTALL})")
    print(f"{'n':>5} {'dofs':>7} {'optimum':>8} {'target':>8} {'error':>8} {'outer':>5} "
          f"{'inner':>6} {'start':>6} {'import':>6} {'assem':>6} {'compile':>7} {'solve':>6} "
          f"{'exit':>5} {'whole [s]':>9} {'peer [s]':>8} {'peer err':>8} {'ratio':>6} "
          f"{'cache':>5}  goal")
    for n, cache in itertools.product(args.sizes, caches):
        optimum = math.nan if args.target is not None else mother_optimum(n)
        b = mother_whole_process(n, repeats=args.repeats, target=args.target, K=K,
                                 inner_rtol=inner_rtol, preconditioner=preconditioner,
                                 cache=cache, peer_python=args.peer_python,
                                 solver=args.solver)
        goal = "-" if b.goal_met is None else (
            f"<= {b.peer.goal_ratio:g} {'met' if b.goal_met else 'NOT met'}")
        peer = f"{b.peer.seconds:>8.1f} {b.peer.error:>8.2e}" if b.peer else f"{'-':>8} {'-':>8}"
        print(f"{b.n:>5} {b.dofs:>7} {optimum:>8.2e} {b.target:>8.2e} {b.error:>8.2e} "
              f"{b.outer_iterations:>5} {b.inner_iterations:>6} {b.start_s:>6.2f} "
              f"{b.import_s:>6.2f} {b.assembly_s:>6.2f} {b.compile_s:>7.2f} {b.solve_s:>6.2f} "
              f"{b.exit_s:>5.2f} {b.whole_s:>9.2f} {peer} {b.ratio:>6.2f} {b.cache:>5}  {goal}",
              flush=True)
    print(f"whole: median wall time of {args.repeats} fresh process(es) per size and side "
          "(Python start, imports, mesh, assembly, compilation, optimisation, exit), the "
          "peer's alternated with the project's; phases: medians inside the process; exit: "
          "from its last print to its end (the interpreter's shutdown); start = whole - "
          "phases - exit; outer: MINRES (kkt) or reduced-Hessian CG iterations; inner: AMG "
          "V-cycles (kkt) or primal + adjoint state-solve PCG iterations (Riesz-map mass "
          "solves apart); optimum: relative L2 error of f at the discrete optimum, target: "
          "1 % above it, error: where the run stopped (all against the analytic optimum); "
          "peer err: the peer's own final error (L-BFGS-B, its tutorial's tolerances); cache: "
          "cold = the program (the peer's forms) compiled in the process, warm = loaded from "
          "a cache one untimed process filled (no goal: the goal's time includes compiling)")


def _bench_prdp(args) -> None:
    from .._atomic import write_csv_atomic
    from .._lock import directory_lock
    from ..bench.inverse import prdp_saving, saving_configurations
    from ..studies.cluster import executor_client

    clients = executor_client(args.executor)  # checked before anything is made
    scenes, instances = _saving_instances(args)
    out = _bench_directory(args)
    runs = sum(len(saving_configurations(scene)) * args.repeats for _, scene in instances)
    print(f"PRDP saving: {len(instances)} problem instance(s), {runs} run(s) into {out}/",
          flush=True)
    bars, rows = Bars(runs), []
    with directory_lock(out):  # one writer: a second bench on ``out`` fails at once
        with interrupt_kept(bars, f"finished runs are kept in {out}/ (continue with: "
                                   f"{_bench_prdp_command(args, out)})"):
            with clients as client:
                for seed, scene in instances:
                    rows += prdp_saving(scene, repeats=args.repeats,
                                        out=out / _instance_name(scene.name, seed),
                                        resume=args.resume, progress=bars, client=client)
        bars.close()
        tables = _print_saving(rows, seeded=args.seeds is not None, repeats=args.repeats)
        for name, table in tables.items():
            write_csv_atomic(out / name, table)
    if bars.skipped:
        print(f"{bars.skipped} of {runs} run(s) read back from {out}/, as timed in an earlier "
              "process" + ("" if bars.skipped == runs else
                           ": a saving may compare runs timed in different processes"))
    print(f"wrote {out}/: {', '.join(tables)}, and the studies in "
          f"{', '.join(scene.name + '/' for scene in scenes)}")


def _saving_instances(args) -> tuple[list, list]:
    """``bench prdp``'s scenes and ``(seed, scene)`` instances, every option and scene
    checked before the first study runs."""
    from ..bench.inverse import SAVING_SCENES, saving_configurations, seed_variants

    if args.steps is not None and args.steps < 1:
        raise SolverConfigError(f"--steps {args.steps}: expected an integer >= 1")
    if args.repeats < 1:
        raise SolverConfigError(f"--repeats {args.repeats}: expected an integer >= 1")
    scenes = bench_scenes(args, SAVING_SCENES, (BENCH_MANIFEST, SAVING_TABLE, SEED_TABLE))
    instances = []
    for scene in scenes:
        saving_configurations(scene)
        instances += seed_variants(scene, args.seeds)
    return scenes, instances


def bench_scenes(args, defaults, files) -> list:
    """A seeded benchmark's scenes (``--scene``, else ``defaults``), its ``--seeds`` and
    ``--resume`` checked first, and each scene named so that it can be a directory of
    ``--out`` beside the benchmark's ``files``."""
    if args.seeds is not None and (min(args.seeds) < 0 or len(set(args.seeds)) < len(args.seeds)):
        raise SolverConfigError(f"--seeds {' '.join(map(str, args.seeds))}: expected distinct "
                                "integers >= 0")
    if args.resume and args.out is None:
        raise SolverConfigError("--resume: expected --out DIR, the directory of the run to "
                                "continue")
    scenes = [scene_for(name, args.steps) for name in (args.scene or defaults)]
    names = [scene.name for scene in scenes]
    reserved = (".", "..", *files)
    for name in names:  # each names a directory of the output
        if name in reserved or "/" in name or "\\" in name:
            raise SolverConfigError(f"--scene: a scene named {name!r}; expected a name that "
                                    "can be a directory of --out (no '/' or '\\', not one of "
                                    f"{', '.join(reserved)})")
    # the rows, the summary and the directories go by the scene's name (whatever the case)
    if len({name.casefold() for name in names}) < len(names):
        raise SolverConfigError(f"--scene {' '.join(args.scene)}: scenes named {names}; "
                                "expected scenes of distinct names")
    return scenes


def _bench_directory(args) -> Path:
    """``bench prdp``'s output directory (:func:`bench_directory`)."""
    return bench_directory(args.out, args.resume, {"scene": args.scene, "steps": args.steps,
                                                   "repeats": args.repeats,
                                                   "seeds": args.seeds}, "prdp")


def bench_directory(out: Path | None, resume: bool, options: dict, bench: str) -> Path:
    """A seeded benchmark's output directory, with its manifest of the options: a new or
    empty ``out`` (default: a new ``./bench-<bench>``), or, resumed, one written with the same
    options (its studies would otherwise start afresh beside the old ones, or fail late)."""
    from .._atomic import write_text_atomic

    out = fresh_directory(f"bench-{bench}") if out is None else out
    manifest = out / BENCH_MANIFEST
    if resume:
        try:
            before = json.loads(manifest.read_text())
        except (OSError, json.JSONDecodeError):
            raise SolverConfigError(f"--resume: {manifest} is missing or unreadable; expected "
                                    f"the --out of an earlier bench {bench} run") from None
        changed = [f"--{key}" for key in options if before.get(key) != options[key]]
        if changed:
            raise SolverConfigError(
                f"--resume: {out} was run with other {', '.join(changed)} ({before}); expected "
                "the options of the run it continues")
        return out
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SolverConfigError(f"--out {out}: is not empty; expected a new or empty "
                                "directory, or --resume to continue the run in it")
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(manifest, json.dumps(options, indent=2) + "\n")
    return out


def _instance_name(scene: str, seed: int | None) -> str:
    """An instance's directory under ``bench prdp``'s output: the scene, then its seed."""
    return scene if seed is None else f"{scene}/seed-{seed}"


def _bench_prdp_command(args, out: Path) -> str:
    """The command line that continues this ``bench prdp`` run."""
    words = ["prdp-fem", "bench", "prdp"]
    if args.scene:
        words += ["--scene", *args.scene]
    if args.steps is not None:
        words += ["--steps", str(args.steps)]
    if args.repeats != 1:
        words += ["--repeats", str(args.repeats)]
    if args.seeds is not None:
        words += ["--seeds", *map(str, args.seeds)]
    if args.executor != "serial":
        words += ["--executor", args.executor]
    return shlex.join([*words, "--out", str(out), "--resume"])


def _print_saving(rows, *, seeded: bool, repeats: int) -> dict[str, list[dict]]:
    """Print ``bench prdp``'s table (and the summary over the seeds); return the tables to
    write, every figure at full precision, with the goal's readings."""
    from ..bench.inverse import seed_summary

    cells = [_saving_cells(row, seeded) for row in rows]
    print_table(cells, list(cells[0]))
    tables = {SAVING_TABLE: [{**row._asdict(), "error_difference": row.error_difference,
                              "met": row.goal_met}
                             for row in rows]}
    if seeded:
        print()
        per_run = seed_summary(rows)
        summary = [_seed_cells(one_run) for one_run in per_run]
        print_table(summary, list(summary[0]))
        tables[SEED_TABLE] = [one_run._asdict() for one_run in per_run]
    medians = (f"medians of {repeats} studies run one after another (save_t range: the "
               "lowest and highest time saving among them); " if repeats > 1 else "")
    print(medians + "save: 1 - (run time or CG iterations of the PRDP run up to the step from "
          "which its parameter error stays within +-1 % of the converged run's final error e* "
          "(band@)) / (the same for the converged run: its own time to that band, not its "
          "whole run); times exclude compilation; err_diff: (PRDP - converged) / converged "
          "final error; met: save_t >= 80 % and |err_diff| <= 1 %; below: the final error is "
          "at most 1.01 e* (a run that ends below the band has not reached it: no saving)" + (
              "; per seed (inverse.seed: noise and random sensors; '-': the scene's data draw "
              "nothing), then per run over the seeds: band, met, below: instances that reach "
              "the band / meet the goal / end at or below; medians of the savings over the "
              "instances that reach the band" if seeded else ""))
    return tables


def _saving_cells(row, seeded: bool = False) -> dict:
    def step(value):
        return "-" if value is None else value

    return {"scene": row.scene, "run": row.run,
            **({"seed": step(row.seed)} if seeded else {}), "conv_s": row.converged_s,
            "conv_its": row.converged_iterations, "prdp_s": row.prdp_s,
            "prdp_its": row.prdp_iterations, "band@": step(row.reached_step),
            "save_t": percent(row.time_saving),
            **({"save_t_range": percent_range(row.time_saving_low, row.time_saving_high)}
               if row.repeats > 1 else {}),
            "save_its": percent(row.iteration_saving),
            "err_diff": percent(row.error_difference, digits=2),
            "met": "yes" if row.goal_met else "no",
            "below": "yes" if row.ends_at_or_below else "no"}


def _seed_cells(summary) -> dict:
    """A row of ``bench prdp --seeds``' summary: the goal met in how many instances."""
    return {"scene": summary.scene, "run": summary.run,
            "band": f"{summary.reached}/{summary.instances}",
            "met": f"{summary.met}/{summary.instances}",
            "below": f"{summary.ends_below}/{summary.instances}",
            "median save_t": percent(summary.time_saving),
            "median save_its": percent(summary.iteration_saving),
            "median err_diff": percent(summary.error_difference, digits=2)}


def bench_command(args) -> None:
    return {"cg": _bench_cg, "amg": _bench_amg, "memory": _bench_memory,
            "mother": _bench_mother, "prdp": _bench_prdp, "batch": _bench_batch,
            "descent": _bench_descent, "scale": _bench_scale,
            "learning": _bench_learning}[args.bench](args)


def _bench_learning(args) -> None:
    from .bench_learning import bench_learning

    bench_learning(args)


def _bench_descent(args) -> None:
    from .._atomic import write_csv_atomic
    from .._lock import directory_lock
    from ..bench.descent import descent_rows
    from ..bench.inverse import SAVING_SCENES

    scenes = [scene_for(name, args.steps) for name in (args.scene or SAVING_SCENES)]
    if args.steps is not None and args.steps < 1:
        raise SolverConfigError(f"--steps {args.steps}: expected an integer >= 1")
    out = fresh_directory("bench-descent") if args.out is None else args.out
    if out.exists() and (not out.is_dir() or (out / DESCENT_TABLE).exists()):
        raise SolverConfigError(f"--out {out}: holds a {DESCENT_TABLE} already; expected a "
                                "new directory or one without it")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    with directory_lock(out):
        for scene in scenes:
            print(f"{scene.name}: ", end="", flush=True)
            rows += descent_rows(scene, progress=lambda name: print(f"{name}; ", end="",
                                                                    flush=True))
            print(flush=True)
        cells = [{"scene": r.scene, "run": r.run, "rule": r.rule, "steps": r.steps,
                  "descend": f"{r.descending}/{r.moved}", "fraction": percent(r.fraction),
                  "approach": percent(r.approach_fraction), "cos": r.median_cosine,
                  "err_gap": percent(r.error_gap, 1),
                  "band@": "-" if r.settled_step is None else r.settled_step,
                  "save_t": percent(r.time_saving), "save_cg": percent(r.iteration_saving)}
                 for r in rows]
        print_table(cells, list(cells[0]))
        print("descend: steps that moved along a descent direction of the converged objective "
              "(slope of J at rtol 1e-10 < 0) / steps that moved; approach: the same up to the "
              "step from which the run stays within +-1 % of the converged run's final error "
              "(band@); cos: median cosine between a step and the converged steepest descent; "
              "save: 1 - time or CG iterations to band@ / the converged run's own (times "
              "exclude compilation)")
        write_csv_atomic(out / DESCENT_TABLE, [row._asdict() for row in rows])
    print(f"wrote {out / DESCENT_TABLE}")


#: What ``bench descent`` writes.
DESCENT_TABLE = "descent.csv"
