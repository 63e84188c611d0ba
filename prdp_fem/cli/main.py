"""The ``prdp-fem`` command.

Subcommands
-----------
``study``      sweep a scene's configurations: results.jsonl, summary.csv, figures, fields
``invert``     one inversion with the scene's own settings (same outputs)
``solve``      forward solve of a scene or a bare mesh file, written as VTU
``mesh-info``  cells, quality, tags and problems of a mesh file
``scenes``     list the built-in scenes, or print one
``forward``    truncated-PCG error against K and run time (a quick forward study)
``stability``  the stiff/extreme-case suite: a Markdown + CSV table; exit 1 on any failure
``bench cg``   PCG iteration / SciPy SpMV time ratio, and its slope against the dofs
``bench memory``  peak memory and time of a gradient through PCG, per gradient mode and K
``bench amg``  AMG-PCG against pyamg's own CG solve
``bench mother``  whole-process time and error on dolfin-adjoint's mother problem, against it
``bench prdp``    the PRDP saving against the converged run on the built-in inverse scenes
``bench descent`` how often each refinement rule's steps descend the converged objective

Bad input (a scene, a mesh file, an option) prints one line ``prdp-fem: error: ...`` and exits
with status 2, no traceback. Anything else that goes wrong (a bug, memory running out) prints
one line ``prdp-fem: internal error: TYPE: ...`` and exits with status 2 too (1 is kept for a
check that ran and failed: ``stability``); ``--debug`` shows the
traceback instead. Ctrl-C during a study lets the running step finish and write its record,
then exits with 130, every finished record kept; a second Ctrl-C stops at once. A scene whose
mesh would carry more than ``--max-dofs`` degrees of freedom (default 20,000,000, or the
environment variable PRDP_FEM_MAX_DOFS) is refused before anything is built.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import gc
import itertools
import json
import math
import os
import shlex
import signal
import sys
import threading
import time
from pathlib import Path

from .._version import __version__
from ..errors import PrdpFemError, SceneError, SolverConfigError

DEFAULT_ITERATIONS = [0, 5, 10, 20, 40, 80, 160, 320, 640]
DEFAULT_INNER_K = 5  # prdp_fem.bench.inverse.DEFAULT_K (not imported here: jax loads slowly)
MESH_SUFFIXES = (".msh", ".vtu", ".vtk", ".xdmf", ".xmf", ".mesh", ".med", ".inp", ".obj",
                 ".ply", ".stl", ".off", ".dat", ".su2", ".avs", ".f3grid", ".h5m", ".ugrid")

EXAMPLES = {
    "study": """examples:
  prdp-fem study                               # the main job (cube_kappa), into ./study-cube_kappa
  prdp-fem study mother                        # dolfin-adjoint's mother problem
  prdp-fem study inclusion --out runs/incl     # a built-in scene
  prdp-fem study my_scene.toml --steps 20      # your scene, fewer optimiser steps
  prdp-fem study my_scene.toml --out runs/a --resume   # continue a killed study""",
    "invert": """examples:
  prdp-fem invert plate_hole --out runs/plate
  prdp-fem invert my_scene.toml --steps 50""",
    "solve": """examples:
  prdp-fem solve meshes/plate_hole.msh                # -lap u = 1, u = 0 on the boundary
  prdp-fem solve poisson_h --reference --out u.vtu    # a scene; error against pyamg""",
    "mesh-info": """examples:
  prdp-fem mesh-info meshes/cube_tet.msh""",
    "stability": """examples:
  prdp-fem stability                          # all cases, into ./stability
  prdp-fem stability --fast --out runs/stab   # the subset the default tests run
  prdp-fem stability --case inclusion_1e10 aspect_1e4""",
    "scenes": """examples:
  prdp-fem scenes                 # list
  prdp-fem scenes mother > my.toml   # copy one to edit""",
}


def _common(defaults: bool) -> argparse.ArgumentParser:
    """The options every command takes (before or after its name): ``--debug`` and
    ``--max-dofs``; a command's copy leaves them unset unless given (``SUPPRESS``), so that
    one given before the command's name is not reset by it."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true",
                        default=False if defaults else argparse.SUPPRESS,
                        help="show the traceback of an error instead of its one line")
    common.add_argument("--max-dofs", type=int, metavar="N",
                        default=None if defaults else argparse.SUPPRESS,
                        help="refuse a scene whose mesh would carry more than N degrees of "
                        "freedom (default: PRDP_FEM_MAX_DOFS, else 20000000)")
    return common


def _command(sub, name: str, help_text: str, **kwargs) -> argparse.ArgumentParser:
    return sub.add_parser(name, help=help_text, description=help_text,
                          epilog=EXAMPLES.get(name), parents=[_common(False)],
                          formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)


def _plain(text: str) -> str:
    """Docstring text for a terminal: reST's double backquotes dropped."""
    return text.replace("``", "")


def _parser() -> argparse.ArgumentParser:
    epilog = __doc__.split("\n\n")[1]  # the module docstring's list of subcommands
    parser = argparse.ArgumentParser(prog="prdp-fem", description=_plain(__doc__.split("\n")[0]),
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=_plain(epilog), parents=[_common(True)])
    parser.add_argument("--version", action="version", version=f"prdp-fem {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    study = _command(sub, "study", "sweep a scene's configurations; tables and figures of "
                     "error against run time and CG iterations")
    study.add_argument("scene", nargs="?", default="cube_kappa",
                       help="a scene .toml file or a built-in scene name (default: cube_kappa, "
                       "the main job)")
    study.add_argument("--out", type=Path, help="output directory (default: ./study-SCENE, "
                       "numbered when it exists)")
    study.add_argument("--resume", action="store_true",
                       help="continue the study in --out, skipping finished configurations")
    study.add_argument("--steps", type=int,
                       help="optimiser steps, or epochs of a learned or heat study (overrides "
                       "the scene)")

    invert = _command(sub, "invert", "one inversion with the scene's settings")
    invert.add_argument("scene", help="a scene .toml file or a built-in scene name")
    invert.add_argument("--out", type=Path, help="output directory (default: ./invert-SCENE)")
    invert.add_argument("--steps", type=int, help="optimiser steps (overrides the scene)")

    solve = _command(sub, "solve", "forward solve of a scene or a mesh file, written as VTU")
    solve.add_argument("input", help="a scene (.toml or built-in name) or a mesh file")
    solve.add_argument("--out", type=Path, help="VTU file (default: ./NAME-solution.vtu)")
    solve.add_argument("--iterations", type=int, help="truncate PCG at K iterations")
    solve.add_argument("--reference", action="store_true",
                       help="also solve with pyamg and report the relative error")

    info = _command(sub, "mesh-info", "cells, quality, tags and problems of a mesh file",
                    aliases=["mesh"])
    info.add_argument("path", type=Path)

    scenes = _command(sub, "scenes", "list the built-in scenes, or print one as TOML")
    scenes.add_argument("name", nargs="?")

    forward = _command(sub, "forward", "error of truncated PCG against K and time")
    forward.add_argument("--scene", default="square", help="square | hole | lshape | cube")
    forward.add_argument("--mesh", help="a mesh file instead of a built-in scene")
    forward.add_argument("--n", type=int, default=128, help="resolution of the scene")
    forward.add_argument("--element", default="P1", help="P1 | P2 | Q1 | Q2")
    forward.add_argument("--iterations", type=int, nargs="+", default=DEFAULT_ITERATIONS,
                         metavar="K", help="the K values to run")
    forward.add_argument("--preconditioner", default="jacobi", help="jacobi | identity")
    forward.add_argument("--out", type=Path, help="append records as JSON lines here")

    stability = _command(sub, "stability", "run the stability suite (contrast, anisotropy, "
                         "bad meshes, scales, pure Neumann, K extremes, float32)")
    stability.add_argument("--out", type=Path, default=Path("stability"),
                           help="directory for stability.md and stability.csv "
                           "(default: ./stability)")
    stability.add_argument("--case", nargs="+", metavar="NAME", help="only these cases")
    stability.add_argument("--fast", action="store_true", help="only the fast subset")

    bench = _command(sub, "bench", "benchmarks")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    bench_sub.add_parser = functools.partial(bench_sub.add_parser, parents=[_common(False)])
    cg = bench_sub.add_parser("cg", help="PCG iteration time / SciPy SpMV time, and its "
                              "scaling with the number of dofs")
    cg.add_argument("--dim", type=int, choices=(2, 3), default=2,
                    help="unit square (P1 triangles) or unit cube (P1 tetrahedra)")
    cg.add_argument("--sides", type=int, nargs="+", default=None,
                    help="cells per side ((n-1)^dim dofs); default 2-D: 128 256 512 1024 "
                    "(16k .. 1M dofs), 3-D: 32 48 64 80 (30k .. 493k)")
    cg.add_argument("--reference", choices=("auto", "scipy", "device"), default="auto",
                    help="the SpMV an iteration is compared with: SciPy's CSR on the host, or "
                    "the device's CSR SpMV timing every kernel (auto: device on an "
                    "accelerator)")
    cg.add_argument("--iterations", type=int, default=100)
    cg.add_argument("--repeats", type=int, default=7)
    memory = bench_sub.add_parser(
        "memory", help="peak memory and time of one gradient through PCG (unrolled, "
        "unrolled with checkpoints, implicit), each in a fresh process")
    memory.add_argument("--side", type=int, default=257,
                        help="unit-square cells per side ((n-1)^2 dofs: 257 -> 65536)")
    memory.add_argument("--iterations", type=int, nargs="+", default=[10, 100, 1000],
                        metavar="K", help="the K values to run")
    memory.add_argument("--modes", nargs="+", default=["unrolled", "checkpointed", "implicit"],
                        metavar="MODE", help="unrolled | checkpointed | implicit")
    memory.add_argument("--segment", type=int,
                        help="checkpointed segment length (default: ceil(sqrt(K)))")
    memory.add_argument("--repeats", type=int, default=3, help="timed gradient evaluations")
    memory.add_argument("--max-mb", type=float, default=4000.0,
                        help="skip running a configuration whose XLA scratch estimate exceeds "
                        "this (MB; it is still compiled and its estimate reported)")
    memory.add_argument("--allocator", choices=["default", "reuse", "both"], default="default",
                        help="glibc's allocator as it comes, or told to keep freed memory "
                        "mapped (MALLOC_ARENA_MAX=1 MALLOC_MMAP_MAX_=0 "
                        "MALLOC_TRIM_THRESHOLD_=4294967296); both: each configuration "
                        "under both, interleaved, with the time ratio reuse / default")
    amg = bench_sub.add_parser("amg", help="AMG-PCG iterations and time / pyamg's own CG solve")
    amg.add_argument("--sides", type=int, nargs="*", default=[256, 512],
                     help="unit-square cells per side ((n-1)^2 dofs: 256 -> 65k, 512 -> 261k)")
    amg.add_argument("--cube-sides", type=int, nargs="*", default=[32],
                     help="unit-cube cells per side ((n-1)^3 dofs: 32 -> 30k, 64 -> 250k)")
    amg.add_argument("--implementations", nargs="+", default=["jax", "callback"],
                     help="jax | callback")
    amg.add_argument("--repeats", type=int, default=5, help="timed pairs (median)")
    mother = bench_sub.add_parser(
        "mother", help="mother problem: whole-process time and error against dolfin-adjoint",
        description="dolfin-adjoint's Poisson mother problem (P1/P1, alpha = 1e-6) solved by "
        "CG on the reduced Hessian with truncated inner PCG, each run a fresh process, until "
        "the relative L2 error of f reaches the peer's (see prdp_fem.bench.inverse)")
    mother.add_argument("--sizes", type=int, nargs="+", default=[256, 512],
                        help="unit-square cells per side (peer figures at 128, 256, 512)")
    mother.add_argument("--repeats", type=int, default=3,
                        help="fresh processes per size (the median is reported)")
    mother.add_argument("--target", type=float, metavar="E",
                        help="relative L2 error of f to reach (default: the peer's at each size; "
                        "needed at other sizes)")
    mother.add_argument("--iterations", type=int, default=DEFAULT_INNER_K, metavar="K",
                        help="K0 = dK of PRDP on the inner state and adjoint PCG solves "
                        f"(default {DEFAULT_INNER_K})")
    mother.add_argument("--inner-rtol", type=float, metavar="R",
                        help="instead: every inner solve to the relative residual R")
    mother.add_argument("--preconditioner", default="jacobi",
                        help="of the inner PCG: jacobi | identity")
    mother.add_argument("--cache", choices=["cold", "warm", "both"], default="cold",
                        help="cold: every process compiles its program (the goal's reading); "
                        "warm: the processes load it from a compilation cache one untimed "
                        "process filled, as a script does from its second run on; both: a "
                        "row of each per size")
    saving = bench_sub.add_parser(
        "prdp", help="PRDP saving against the converged run, per built-in inverse scene",
        description="run each scene's converged reference and its PRDP configurations (a "
        "study) and print the saving: time and CG iterations to reach the converged run's "
        "final error, against the converged run's own time and iterations to it")
    _add_inverse_scenes(saving)
    saving.add_argument("--repeats", type=int, default=1,
                        help="studies per scene, run one after another; the table shows "
                        "medians and the range of the time saving (default 1)")
    saving.add_argument("--seeds", type=int, nargs="+", default=None, metavar="SEED",
                        help="run each scene once per noise and sensor seed (inverse.seed; "
                        "a scene whose data draw nothing runs once) and add a summary: per "
                        "run, how many of these problem instances meet the goal, and the "
                        "median savings")
    saving.add_argument("--out", type=Path, help="where the studies go, one directory per "
                        "scene and seed, and the tables (saving.csv, seeds.csv) at the end "
                        "(default: a new ./bench-prdp)")
    saving.add_argument("--resume", action="store_true",
                        help="continue the run in --out (same options): its finished runs are "
                        "read back (times as measured then), the rest run")
    descent = bench_sub.add_parser(
        "descent", help="how often each refinement rule's steps descend the converged "
        "objective, and its saving",
        description="run each scene's converged reference, its PRDP and fixed runs and an "
        "adaptive run (refinement.kind = 'adaptive', residual-aware) and check every step "
        "against a converged gradient: the fraction of steps that descend the converged "
        "objective, and each run's same-target saving")
    _add_inverse_scenes(descent)
    descent.add_argument("--out", type=Path, help="where descent.csv goes (default: a new "
                         "./bench-descent)")
    return parser


def _add_inverse_scenes(parser: argparse.ArgumentParser) -> None:
    """``--scene`` and ``--steps`` of the benchmarks that run the built-in inverse scenes."""
    parser.add_argument("--scene", nargs="+", default=None, metavar="SCENE",
                        help="scene files or built-in names (default: mother inclusion "
                        "plate_hole cube)")
    parser.add_argument("--steps", type=int, help="optimiser steps (overrides the scenes)")


# --------------------------------------------------------------------------------------
# progress bars (quiet when stderr is not a terminal)
# --------------------------------------------------------------------------------------


class _Interrupted(Exception):
    """Ctrl-C during a study: the message says where the finished records are."""


def _is_interrupt(error: BaseException) -> bool:
    """Ctrl-C, also when it lands inside a JAX host callback (the iteration counter's taps):
    JAX re-raises it there wrapped in a ``JaxRuntimeError`` that names ``KeyboardInterrupt``."""
    return isinstance(error, KeyboardInterrupt) or (
        type(error).__name__ == "JaxRuntimeError" and "KeyboardInterrupt" in str(error))


class _Bars:
    """tqdm bars over configurations and optimiser steps
    (:class:`prdp_fem.studies.runner.Progress`).

    Also where a requested stop (:func:`_stop_between_steps`) takes effect: after a step's
    record is written, in the main thread, outside any JAX computation.
    """

    def __init__(self, total: int):
        from tqdm import tqdm

        self._tqdm = tqdm
        self._quiet = not sys.stderr.isatty()
        self._outer = tqdm(total=total, desc="configurations", position=0,
                           disable=self._quiet, leave=True)
        self._inner = None
        self.stop_requested = False
        self.skipped = 0  # runs found done already (a resumed study), not run again

    def run_started(self, name: str, steps: int) -> None:
        self._inner = self._tqdm(total=steps, desc=name[:28], position=1, leave=False,
                                 disable=self._quiet)

    def step(self) -> None:
        if self._inner is not None:
            self._inner.update()
        self.stop_if_requested()

    def run_finished(self, name: str, skipped: bool) -> None:
        if self._inner is not None:
            self._inner.close()
            self._inner = None
        self._outer.update()
        if skipped:
            self.skipped += 1
            self._outer.write(f"{name}: done already, skipped")
        self.stop_if_requested()

    def stop_if_requested(self) -> None:
        """Stop here (``KeyboardInterrupt``) if a Ctrl-C asked for it: between two steps, or
        two studies of a benchmark."""
        if self.stop_requested:
            raise KeyboardInterrupt

    def close(self) -> None:
        self._outer.close()


# --------------------------------------------------------------------------------------
# commands
# --------------------------------------------------------------------------------------


def _scene(name_or_path: str, steps: int | None):
    from ..scene.spec import load_scene, with_overrides

    scene = load_scene(name_or_path)
    if steps is not None:
        if steps < 0:
            raise SolverConfigError(f"--steps {steps}: expected an integer >= 0")
        kind = scene.study.kind
        if kind in ("learned", "heat"):  # learned and heat studies count epochs
            if steps < 1:
                raise SolverConfigError(f"--steps {steps}: a {kind} study's epochs; "
                                        "expected an integer >= 1")
            scene = with_overrides(scene, {kind: {"epochs": steps}})
        else:
            scene = with_overrides(scene, {"optimizer": {"steps": steps}})
    return scene


def _fresh_directory(stem: str) -> Path:
    path, number = Path(stem), 2
    while path.exists() and any(path.iterdir()):
        path, number = Path(f"{stem}-{number}"), number + 1
    return path


def _format(value) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.4g}"
    return str(value)


def _print_table(rows: list[dict], columns: list[str]) -> None:
    cells = [[_format(row.get(c, "")) for c in columns] for row in rows]
    widths = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(columns)]
    print("  ".join(c.rjust(w) for c, w in zip(columns, widths, strict=True)))
    for row in cells:
        print("  ".join(v.rjust(w) for v, w in zip(row, widths, strict=True)))


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


@contextlib.contextmanager
def _stop_between_steps(bars: _Bars):
    """The first Ctrl-C stops the study after the step it is in; a second one at once.

    Python raises ``KeyboardInterrupt`` wherever the main thread is, and during a jitted step
    that can be inside a host callback (the iteration counter's taps). A loaded test run once
    hung there for minutes instead of exiting. A flag read between steps keeps the
    exception out of JAX; the step in flight finishes and its record is kept.
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be set from the main thread
        return

    def request_stop(signum, frame):
        bars.stop_requested = True
        signal.signal(signal.SIGINT, signal.default_int_handler)  # the next one interrupts

    previous = signal.signal(signal.SIGINT, request_stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def _interrupt_kept(bars: _Bars, kept: str):
    """A block in which the first Ctrl-C stops after the step in flight
    (:func:`_stop_between_steps`) and the interrupt leaves as one line: ``kept`` says what
    is kept and how to continue."""
    try:
        with _stop_between_steps(bars):
            yield
    except (KeyboardInterrupt, RuntimeError) as error:  # JaxRuntimeError is a RuntimeError
        if not _is_interrupt(error):
            raise
        bars.close()
        raise _Interrupted(f"interrupted; {kept}") from None


def _run_study(scene, out: Path | None, resume: bool, prefix: str) -> None:
    from ..studies.runner import RESULTS, SUMMARY, configurations, run_study

    if out is None:
        out = Path(f"{prefix}-{scene.name}") if resume else _fresh_directory(
            f"{prefix}-{scene.name}")
    print(f"{scene.name} ({scene.source}): {scene.study.kind} study of "
          f"{len(configurations(scene))} configuration(s) into {out}/", flush=True)
    bars = _Bars(len(configurations(scene)))
    continued = shlex.join(["prdp-fem", "study", str(scene.source), "--out", str(out),
                            "--resume"])
    with _interrupt_kept(bars, f"finished records are kept in {out}/{RESULTS} (continue "
                               f"with: {continued})"):
        result = run_study(scene, out, resume=resume, progress=bars)
    bars.close()
    # the table opens with its plain reading: the scene's PRDP run against its reference
    headline = _headline(scene, result.summary) if scene.study.kind == "inverse" else None
    if headline:
        print(headline)
    _print_table(result.summary, SUMMARY_COLUMNS[scene.study.kind])
    figures = ", ".join(str(p.relative_to(out)) for p in result.figures)
    print(f"\nwrote {out}/: {RESULTS}, {SUMMARY}, {figures}"
          + (", fields/*.vtu" if scene.study.kind == "inverse" else ""))


def _headline(scene, summary: list[dict]) -> str | None:
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


def _study(args) -> None:
    _run_study(_scene(args.scene, args.steps), args.out, args.resume, "study")


def _invert(args) -> None:
    scene = _scene(args.scene, args.steps)
    if scene.inverse is None:
        raise SceneError(f"{scene.source}: no [inverse] section; expected one to invert")
    study = dataclasses.replace(scene.study, kind="inverse", runs=((scene.name, "{}"),))
    _run_study(dataclasses.replace(scene, study=study), args.out, False, "invert")


def _is_mesh_file(text: str) -> bool:
    return Path(text).suffix.lower() in MESH_SUFFIXES


def _solve(args) -> None:
    from ..mesh.vtu import write_vtu
    from ..scene.build import forward_solve
    from ..scene.spec import load_scene, mesh_scene, with_overrides

    scene = mesh_scene(args.input) if _is_mesh_file(args.input) else load_scene(args.input)
    if args.iterations is not None:
        if args.iterations < 0:
            raise SolverConfigError(f"--iterations {args.iterations}: expected an integer >= 0")
        scene = with_overrides(scene, {"solver": {"iterations": [args.iterations]}})
    result = forward_solve(scene, reference=args.reference)
    out = args.out or Path(f"{scene.name}-solution.vtu")
    write_vtu(result.disc.mesh, out, {"u": ("nodal", result.u),
                                      "kappa": (scene.pde.kappa_space, result.kappa)})
    sol = result.solution
    print(f"{scene.name}: {result.disc.n_free} free dofs, {scene.pde.element}, "
          f"{scene.solver.preconditioner}-PCG {int(sol.iterations)} iterations, residual "
          f"{float(sol.residual_norm):.3e} (initial {float(sol.initial_residual_norm):.3e}), "
          f"{result.solve_time:.4f} s")
    if args.reference and result.reference_failure:
        print(f"reference: {result.reference_failure}; no error against it to report")
    elif args.reference:
        print(f"relative l2 error against pyamg (rtol 1e-12): {result.relative_error:.3e}")
    print(f"wrote {out}")


def _mesh_info(args) -> None:
    import warnings

    from ..errors import MeshError, MeshRepairWarning
    from ..mesh.io import load_mesh, mesh_quality

    problems = []
    try:
        mesh = load_mesh(args.path)
    except MeshError as error:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", MeshRepairWarning)
            try:
                mesh = load_mesh(args.path, repair=True)
            except MeshError:
                raise error from None
        problems.append(f"{error.problem} (repairable: load_mesh(repair=True) or "
                        "mesh.repair = true in a scene)")
        problems += [str(w.message) for w in caught]
    quality = mesh_quality(mesh)
    print(f"{args.path}")
    for field, value in quality._asdict().items():
        print(f"{field:>14}: {_format(value) if isinstance(value, float) else value}")
    for kind, groups in (("boundary", mesh.boundaries), ("subdomain", mesh.subdomains)):
        for name, members in (groups or {}).items():
            print(f"{kind:>14}: {name} ({len(members)})")
    if not mesh.boundaries:
        problems.append("no tagged boundaries: Dirichlet data can only be given for the "
                        "whole boundary")
    if quality.quality_min < 0.1:
        problems.append(f"poorly shaped cells: minimum quality {quality.quality_min:.3g} "
                        "(1 = equilateral); expect slow CG convergence")
    if quality.h_max / quality.h_min > 100:
        problems.append(f"strongly graded: longest / shortest edge = "
                        f"{quality.h_max / quality.h_min:.3g}")
    print(f"{'problems':>14}: {'none found' if not problems else len(problems)}")
    for problem in problems:
        print(f"{'':>14}  - {problem}")
    if quality.n_inverted:
        print(f"{'note':>14}: {quality.n_inverted} cells numbered clockwise (valid as they are)")


def _scenes(args) -> None:
    from ..scene.spec import BUILTIN_SCENES, builtin_scene_path, load_scene

    if args.name is not None:
        print(builtin_scene_path(args.name).read_text(), end="")
        return
    for name in BUILTIN_SCENES:
        scene = load_scene(name)
        print(f"{name:<12} {scene.study.kind:<8} {scene.description}")


def _forward(args) -> None:
    from ..studies.forward import build_scene, forward_convergence

    if any(k < 0 for k in args.iterations):
        raise SolverConfigError(f"--iterations {args.iterations}: expected integers >= 0")
    scene = build_scene(args.scene, n=args.n, element=args.element, mesh_path=args.mesh)
    source = args.mesh or f"scene {args.scene} (n={args.n})"
    print(f"{source}: {scene.disc.n_free} free dofs, {args.element}, "
          f"{args.preconditioner}-PCG, errors against pyamg (rtol 1e-12)")
    print(f"{'K':>6} {'iters':>6} {'time [s]':>10} {'rel L2 err':>12} {'rel energy err':>15}")

    def emit(record):
        print(f"{record.requested_iterations:>6} {record.iterations:>6} "
              f"{record.wall_time_s:>10.4f} {record.relative_l2_error:>12.3e} "
              f"{record.relative_energy_error:>15.3e}", flush=True)
        if args.out is not None:
            from .._atomic import output_error

            try:
                with args.out.open("a") as stream:  # one line per record, as it lands
                    stream.write(json.dumps({"source": source, **record._asdict()}) + "\n")
            except OSError as error:  # a full disk: name the file
                raise output_error(args.out, error) from error

    study = forward_convergence(scene, args.iterations, preconditioner=args.preconditioner,
                                on_record=emit)
    print(f"setup {study.setup_time_s:.2f} s (assembly + reference), "
          f"first-solve compile {study.compile_time_s:.2f} s")


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
        raise SolverConfigError(_as_option(str(error))) from None


def _as_option(message: str) -> str:
    """``max_mb=-1.0: ...`` -> ``--max-mb -1.0: ...``; lists are shown space-separated."""
    name, _, rest = message.partition("=")
    value, _, explanation = rest.partition(": ")
    value = value.strip("[]").replace(",", "").replace("'", "")
    return f"--{name.replace('_', '-')} {value}: {explanation}"


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


def _bench_mother(args) -> None:
    from ..bench.inverse import CACHES, check_mother_options, mother_whole_process

    caches = CACHES if args.cache == "both" else (args.cache,)  # argparse checked the name
    check_mother_options(args.sizes, repeats=args.repeats, target=args.target,
                         K=args.iterations, inner_rtol=args.inner_rtol,
                         preconditioner=args.preconditioner)
    inner = f"PRDP K0 = dK = {args.iterations}" if args.inner_rtol is None else \
        f"rtol {args.inner_rtol:g}"
    print(f"reduced-Hessian CG, inner {args.preconditioner}-PCG: {inner}")
    print(f"{'n':>5} {'dofs':>7} {'target':>8} {'error':>8} {'outer':>5} {'CG its':>6} "
          f"{'start':>6} {'import':>6} {'assem':>6} {'compile':>7} {'solve':>6} {'exit':>5} "
          f"{'whole [s]':>9} {'peer [s]':>8} {'ratio':>6} {'cache':>5}  goal")
    for n, cache in itertools.product(args.sizes, caches):
        b = mother_whole_process(n, repeats=args.repeats, target=args.target, K=args.iterations,
                                 inner_rtol=args.inner_rtol, preconditioner=args.preconditioner,
                                 cache=cache)
        goal = "-" if b.goal_met is None else (
            f"<= {b.peer.goal_ratio:g} {'met' if b.goal_met else 'NOT met'}")
        peer = f"{b.peer.seconds:>8.1f}" if b.peer else f"{'-':>8}"
        print(f"{b.n:>5} {b.dofs:>7} {b.target:>8.1e} {b.error:>8.2e} {b.outer_iterations:>5} "
              f"{b.cg_iterations:>6} {b.start_s:>6.2f} {b.import_s:>6.2f} {b.assembly_s:>6.2f} "
              f"{b.compile_s:>7.2f} {b.solve_s:>6.2f} {b.exit_s:>5.2f} {b.whole_s:>9.2f} "
              f"{peer} {b.ratio:>6.2f} {b.cache:>5}  {goal}", flush=True)
    print(f"whole: median wall time of {args.repeats} fresh process(es) per size (Python start, "
          "imports, mesh, assembly, compilation, optimisation, exit); phases: medians inside "
          "the process; exit: from its last print to its end (the interpreter's shutdown); "
          "start = whole - phases - exit; CG its: primal + adjoint state-solve iterations "
          "(Riesz-map mass solves apart); error: relative L2 of f against the analytic optimum; "
          "cache: cold = the program compiled in the process, warm = loaded from a cache one "
          "untimed process filled (no goal: the goal's time includes compiling)")


def _bench_prdp(args) -> None:
    from .._atomic import write_csv_atomic
    from .._lock import directory_lock
    from ..bench.inverse import prdp_saving, saving_configurations

    scenes, instances = _saving_instances(args)
    out = _bench_directory(args)
    runs = sum(len(saving_configurations(scene)) * args.repeats for _, scene in instances)
    print(f"PRDP saving: {len(instances)} problem instance(s), {runs} run(s) into {out}/",
          flush=True)
    bars, rows = _Bars(runs), []
    with directory_lock(out):  # one writer: a second bench on ``out`` fails at once
        with _interrupt_kept(bars, f"finished runs are kept in {out}/ (continue with: "
                                   f"{_bench_prdp_command(args, out)})"):
            for seed, scene in instances:
                bars.stop_if_requested()  # a Ctrl-C between two studies
                rows += prdp_saving(scene, repeats=args.repeats,
                                    out=out / _instance_name(scene.name, seed),
                                    resume=args.resume, progress=bars)
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


#: What ``bench prdp`` writes at the top of its output directory, besides the studies.
BENCH_MANIFEST, SAVING_TABLE, SEED_TABLE = "bench.json", "saving.csv", "seeds.csv"


def _saving_instances(args) -> tuple[list, list]:
    """``bench prdp``'s scenes and ``(seed, scene)`` instances, every option and scene
    checked before the first study runs."""
    from ..bench.inverse import SAVING_SCENES, saving_configurations, seed_variants

    if args.steps is not None and args.steps < 1:
        raise SolverConfigError(f"--steps {args.steps}: expected an integer >= 1")
    if args.repeats < 1:
        raise SolverConfigError(f"--repeats {args.repeats}: expected an integer >= 1")
    if args.seeds is not None and (min(args.seeds) < 0 or len(set(args.seeds)) < len(args.seeds)):
        raise SolverConfigError(f"--seeds {' '.join(map(str, args.seeds))}: expected distinct "
                                "integers >= 0")
    if args.resume and args.out is None:
        raise SolverConfigError("--resume: expected --out DIR, the directory of the run to "
                                "continue")
    scenes = [_scene(name, args.steps) for name in (args.scene or SAVING_SCENES)]
    names = [scene.name for scene in scenes]
    for name in names:  # each names a directory of the output
        if name in (".", "..", BENCH_MANIFEST, SAVING_TABLE, SEED_TABLE) or "/" in name \
                or "\\" in name:
            raise SolverConfigError(f"--scene: a scene named {name!r}; expected a name that "
                                    "can be a directory of --out (no '/' or '\\', not '.', "
                                    f"'..', {BENCH_MANIFEST}, {SAVING_TABLE} or {SEED_TABLE})")
    # the rows, the summary and the directories go by the scene's name (whatever the case)
    if len({name.casefold() for name in names}) < len(names):
        raise SolverConfigError(f"--scene {' '.join(args.scene)}: scenes named {names}; "
                                "expected scenes of distinct names")
    instances = []
    for scene in scenes:
        saving_configurations(scene)
        instances += seed_variants(scene, args.seeds)
    return scenes, instances


def _bench_directory(args) -> Path:
    """``bench prdp``'s output directory, with its manifest of the options: a new or empty
    ``--out`` (default: a new ``./bench-prdp``), or, resumed, one written with the same
    options (its studies would otherwise start afresh beside the old ones, or fail late)."""
    from .._atomic import write_text_atomic

    options = {"scene": args.scene, "steps": args.steps, "repeats": args.repeats,
               "seeds": args.seeds}
    out = _fresh_directory("bench-prdp") if args.out is None else args.out
    manifest = out / BENCH_MANIFEST
    if args.resume:
        try:
            before = json.loads(manifest.read_text())
        except (OSError, json.JSONDecodeError):
            raise SolverConfigError(f"--resume: {manifest} is missing or unreadable; expected "
                                    "the --out of an earlier bench prdp run") from None
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
    return shlex.join([*words, "--out", str(out), "--resume"])


def _print_saving(rows, *, seeded: bool, repeats: int) -> dict[str, list[dict]]:
    """Print ``bench prdp``'s table (and the summary over the seeds); return the tables to
    write, every figure at full precision, with the goal's readings."""
    from ..bench.inverse import seed_summary

    cells = [_saving_cells(row, seeded) for row in rows]
    _print_table(cells, list(cells[0]))
    tables = {SAVING_TABLE: [{**row._asdict(), "error_difference": row.error_difference,
                              "met": row.goal_met}
                             for row in rows]}
    if seeded:
        print()
        per_run = seed_summary(rows)
        summary = [_seed_cells(one_run) for one_run in per_run]
        _print_table(summary, list(summary[0]))
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
            "save_t": _percent(row.time_saving),
            **({"save_t_range": _percent_range(row.time_saving_low, row.time_saving_high)}
               if row.repeats > 1 else {}),
            "save_its": _percent(row.iteration_saving),
            "err_diff": _percent(row.error_difference, digits=2),
            "met": "yes" if row.goal_met else "no",
            "below": "yes" if row.ends_at_or_below else "no"}


def _seed_cells(summary) -> dict:
    """A row of ``bench prdp --seeds``' summary: the goal met in how many instances."""
    return {"scene": summary.scene, "run": summary.run,
            "band": f"{summary.reached}/{summary.instances}",
            "met": f"{summary.met}/{summary.instances}",
            "below": f"{summary.ends_below}/{summary.instances}",
            "median save_t": _percent(summary.time_saving),
            "median save_its": _percent(summary.iteration_saving),
            "median err_diff": _percent(summary.error_difference, digits=2)}


def _percent(value: float, digits: int = 0) -> str:
    return "-" if math.isnan(value) else f"{100 * value:.{digits}f} %"


def _percent_range(low: float, high: float) -> str:
    return "-" if math.isnan(low) or math.isnan(high) else f"{100 * low:.0f}-{100 * high:.0f} %"


def _bench(args) -> None:
    return {"cg": _bench_cg, "amg": _bench_amg, "memory": _bench_memory,
            "mother": _bench_mother, "prdp": _bench_prdp,
            "descent": _bench_descent}[args.bench](args)


def _bench_descent(args) -> None:
    from .._atomic import write_csv_atomic
    from .._lock import directory_lock
    from ..bench.descent import descent_rows
    from ..bench.inverse import SAVING_SCENES

    scenes = [_scene(name, args.steps) for name in (args.scene or SAVING_SCENES)]
    if args.steps is not None and args.steps < 1:
        raise SolverConfigError(f"--steps {args.steps}: expected an integer >= 1")
    out = _fresh_directory("bench-descent") if args.out is None else args.out
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
                  "descend": f"{r.descending}/{r.moved}", "fraction": _percent(r.fraction),
                  "approach": _percent(r.approach_fraction), "cos": r.median_cosine,
                  "err_gap": _percent(r.error_gap, 1),
                  "band@": "-" if r.settled_step is None else r.settled_step,
                  "save_t": _percent(r.time_saving), "save_cg": _percent(r.iteration_saving)}
                 for r in rows]
        _print_table(cells, list(cells[0]))
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


def _stability(args) -> int:
    from .._atomic import write_text_atomic
    from ..studies.stability import format_markdown, run_case, suite_passed, write_csv
    from ..studies.stability_cases import CASES, case_named

    cases = [case_named(name) for name in args.case] if args.case else \
        [c for c in CASES if c.fast or not args.fast]
    args.out.mkdir(parents=True, exist_ok=True)
    markdown, table = args.out / "stability.md", args.out / "stability.csv"
    results, start = [], time.perf_counter()
    with _progress(len(cases), "cases") as bar:
        for case in cases:
            bar.set_postfix_str(case.name)
            results.append(run_case(case))
            write_csv(results, table)  # after every case: an interrupted run keeps its rows
            write_text_atomic(markdown, format_markdown(results))
            bar.update()
    print(format_markdown(results), end="")
    passed = suite_passed(results)
    failed = [r.case for r in results if r.verdict == "FAIL" or r.nonfinite]
    print(f"{len(results)} cases: {sum(r.verdict == 'ok' for r in results)} ok, "
          f"{sum(r.verdict == 'flagged' for r in results)} flagged, {len(failed)} failed"
          + (f" ({', '.join(failed)})" if failed else "")
          + f" in {time.perf_counter() - start:.0f} s; tables in {markdown}, {table}")
    return 0 if passed else 1


def _progress(total: int, unit: str):
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, disable=not sys.stderr.isatty(), leave=False)


COMMANDS = {"study": _study, "invert": _invert, "solve": _solve, "mesh-info": _mesh_info,
            "mesh": _mesh_info, "scenes": _scenes, "forward": _forward, "bench": _bench,
            "stability": _stability}


def _one_line(text: str) -> str:
    """``text`` as one line of stderr (a message quoting a file's lines keeps them, joined)."""
    return " | ".join(line.strip() for line in str(text).splitlines() if line.strip())


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    debug = getattr(args, "debug", False)
    try:
        return _main(args)
    except PrdpFemError as error:
        if debug:
            raise
        print(f"prdp-fem: error: {_one_line(error)}", file=sys.stderr)
        return 2
    except OSError as error:  # an output path that cannot be written, a full disk
        if debug:
            raise
        where = error.filename or "output"
        print(f"prdp-fem: error: {where}: {_one_line(error.strerror or error)}; expected a "
              "writable path", file=sys.stderr)
        return 2
    except _Interrupted as message:
        print(f"prdp-fem: {message}", file=sys.stderr)
        return 130
    except (KeyboardInterrupt, Exception) as error:  # the last guard: never a traceback
        if _is_interrupt(error):
            print("prdp-fem: interrupted", file=sys.stderr)
            return 130
        if debug:
            raise
        detail = _one_line(error)[:300]
        print(f"prdp-fem: internal error: {type(error).__name__}"
              + (f": {detail}" if detail else "")
              + "; rerun with --debug for the traceback", file=sys.stderr)
        return 2  # every failure of the command is 2; 1 means a check ran and failed


def _main(args) -> int:
    from ..compilation_cache import enable_compilation_cache

    with _max_dofs(args.max_dofs):
        # the program, not the import, switches the persistent compilation cache on: a
        # second run of a command loads the executables the first compiled
        enable_compilation_cache()
        return COMMANDS[args.command](args) or 0


@contextlib.contextmanager
def _max_dofs(value: int | None):
    """``--max-dofs N``: the scenes' dof limit while the command runs (and in the processes it
    starts); the caller's environment is as it was afterwards (``main`` called from Python)."""
    from ..scene.spec import MAX_DOFS_VARIABLE

    if value is None:
        yield
        return
    if value < 1:
        raise SolverConfigError(f"--max-dofs {value}: expected an integer >= 1")
    before = os.environ.get(MAX_DOFS_VARIABLE)
    os.environ[MAX_DOFS_VARIABLE] = str(value)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(MAX_DOFS_VARIABLE, None)
        else:
            os.environ[MAX_DOFS_VARIABLE] = before


def run() -> None:
    """The ``prdp-fem`` program: :func:`main`, then the exit, without Python's last garbage
    collections over the whole heap.

    While Python shuts down it collects garbage several times as it clears the modules; with
    JAX loaded each pass walks some 135,000 objects, 0.2-0.4 s of every command's wall time.
    A command has closed and flushed all it writes by the time :func:`main` returns, so the
    heap is frozen (:func:`gc.freeze`: out of reach of those passes) and left to the exit.
    Only the program does this: :func:`main` called in a live process leaves the heap alone.
    """
    code = main()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    run()
