"""The ``prdp-fem`` command.

Subcommands
-----------
``study``      sweep a scene's configurations: results.jsonl, summary.csv, figures, fields
``invert``     one inversion with the scene's own settings (same outputs)
``evaluate``   test metrics and predictions (VTU, .pvd rollouts) of a learned or heat study
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
``bench learning`` the PRDP saving when training through the solver, over seeds

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
import functools
import gc
import os
import sys
from pathlib import Path

from .._version import __version__
from ..errors import PrdpFemError, SolverConfigError
from ._shared import Interrupted, is_interrupt
from .bench import DEFAULT_INNER_K, bench_command
from .evaluate import evaluate_command
from .forward import DEFAULT_ITERATIONS, forward_command
from .mesh_info import mesh_info_command
from .scenes import scenes_command
from .solve import solve_command
from .stability import stability_command
from .study import invert_command, study_command

EXAMPLES = {
    "study": """examples:
  prdp-fem study                               # the main job (cube_kappa), into ./study-cube_kappa
  prdp-fem study mother                        # dolfin-adjoint's mother problem
  prdp-fem study inclusion --out runs/incl     # a built-in scene
  prdp-fem study my_scene.toml --steps 20      # your scene, fewer optimiser steps
  prdp-fem study my_scene.toml --out runs/a --resume   # continue a killed study
  prdp-fem study inclusion --executor dask     # the configurations on a local Dask cluster
  prdp-fem study reaction_diffusion --seed 3 --out runs/rd-3   # another data and network seed""",
    "evaluate": """examples:
  prdp-fem study learned && prdp-fem evaluate learned    # train, then test metrics + VTU
  prdp-fem evaluate heat.toml --out runs/heat --run "correction wig prdp" --samples 2""",
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
    study.add_argument("--seed", type=int,
                       help="a learned or heat scene's seed: its data, splits and initial "
                       "network (overrides the scene)")
    study.add_argument("--executor", default="serial", metavar="serial|dask[=ADDRESS]",
                       help="where the configurations run: one after another here (serial, "
                       "the default), or as tasks on a Dask cluster, a local one (dask) or a "
                       "running scheduler (dask=tcp://host:8786); needs "
                       "pip install -e '.[cluster]'")

    invert = _command(sub, "invert", "one inversion with the scene's settings")
    invert.add_argument("scene", help="a scene .toml file or a built-in scene name")
    invert.add_argument("--out", type=Path, help="output directory (default: ./invert-SCENE)")
    invert.add_argument("--steps", type=int, help="optimiser steps (overrides the scene)")

    evaluate = _command(sub, "evaluate", "test metrics and predictions of a learned or heat "
                        "study's trained runs (their last checkpoints)")
    evaluate.add_argument("scene", help="the study's scene (.toml file or built-in name)")
    evaluate.add_argument("--out", type=Path, help="the study's directory (default: "
                          "./study-SCENE); evaluation.csv and evaluation/ are written there")
    evaluate.add_argument("--run", nargs="+", metavar="NAME",
                          help="only these runs (default: every run with a checkpoint)")
    evaluate.add_argument("--samples", type=int, default=4,
                          help="test samples or trajectories to write as VTU (default: 4)")
    evaluate.add_argument("--steps", type=int,
                          help="the --steps the study was run with (epochs)")
    evaluate.add_argument("--seed", type=int, help="the --seed the study was run with")

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
        description="dolfin-adjoint's Poisson mother problem (P1/P1, alpha = 1e-6), each run "
        "a fresh process, solved until f is within 1 %% of the discrete optimum's error of "
        "that optimum: by MINRES on its KKT system (--solver kkt) or by CG on the reduced "
        "Hessian through inner PCG solves (--solver reduced); against dolfin-adjoint's "
        "L-BFGS-B in fresh processes alternated with them, where its Python is given (see "
        "prdp_fem.bench.inverse)")
    mother.add_argument("--solver", choices=["kkt", "reduced"], default="kkt",
                        help="kkt: all-at-once MINRES, Pearson-Wathen preconditioner "
                        "(default); reduced: CG on the reduced Hessian")
    mother.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512, 1024],
                        help="unit-square cells per side")
    mother.add_argument("--repeats", type=int, default=5,
                        help="fresh processes per size and side (the median is reported)")
    mother.add_argument("--target", type=float, metavar="E",
                        help="relative L2 error of f to reach (default: 1 %% above the "
                        "discrete optimum's at each size)")
    mother.add_argument("--peer-python", metavar="PYTHON",
                        help="the Python of a legacy FEniCS with dolfin-adjoint 2023.0.0 "
                        "(default: none; the command says how to install one)")
    mother.add_argument("--iterations", type=int, metavar="K",
                        help="--solver reduced: PRDP on the inner state and adjoint PCG "
                        "solves, K0 = dK = K "
                        f"(e.g. {DEFAULT_INNER_K}; default: converged inner solves)")
    mother.add_argument("--inner-rtol", type=float, metavar="R",
                        help="--solver reduced: every inner solve to the relative residual "
                        "R (default 1e-8)")
    mother.add_argument("--preconditioner",
                        help="of the inner PCG of --solver reduced: amg (default) | jacobi | "
                        "identity")
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
    saving.add_argument("--executor", default="serial", metavar="serial|dask[=ADDRESS]",
                        help="where each study's configurations run: here, one after another "
                        "(serial, the default), or as tasks on a Dask cluster (see prdp-fem "
                        "study --help); runs sharing a machine's cores time each other")
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
    learning = bench_sub.add_parser(
        "learning", help="PRDP saving when training through the solver, over seeds",
        description="run each learned or heat scene's study once per seed (its data, splits "
        "and network) and print, per run and seed, the held-out test error and the saving of "
        "each PRDP run against its converged partner (time and CG iterations to the partner's "
        "final test error, against the partner's own), then per run over the seeds and the "
        "orders of the runs by test error (see prdp_fem.bench.learning)")
    learning.add_argument("--scene", nargs="+", default=None, metavar="SCENE",
                          help="learned or heat scene files or built-in names (default: "
                          "heat_emulator reaction_diffusion)")
    learning.add_argument("--steps", type=int, help="epochs (overrides the scenes)")
    learning.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4],
                          metavar="SEED", help="the scenes' seeds (default: 0 1 2 3 4)")
    learning.add_argument("--out", type=Path, help="where the studies go, one directory per "
                          "scene and seed, and the tables (learning.csv, seeds.csv, "
                          "ranking.csv) at the end (default: a new ./bench-learning)")
    learning.add_argument("--resume", action="store_true",
                          help="continue the run in --out (same options): finished runs are "
                          "read back, a killed one continues from its last checkpoint")
    learning.add_argument("--executor", default="serial", metavar="serial|dask[=ADDRESS]",
                          help="where each study's runs go (see prdp-fem study --help)")
    batch = bench_sub.add_parser(
        "batch", help="throughput of batched inversion against a loop of single inversions",
        description="solve 1, 8, 32, 128 source problems that differ in their noise draw by "
        "one invert_batch call (one vmapped program, PRDP per member) and by a Python loop "
        "of invert calls, alternated; problems per second on each side (see "
        "prdp_fem.bench.batch)")
    batch.add_argument("--sizes", type=int, nargs="+", default=[1, 8, 32, 128],
                       help="batch sizes (problems)")
    batch.add_argument("--n", type=int, default=32, help="unit-square cells per side")
    batch.add_argument("--steps", type=int, default=20, help="L-BFGS steps per problem")
    batch.add_argument("--repeats", type=int, default=5,
                       help="alternated timings per size (the median is reported)")
    scale = bench_sub.add_parser(
        "scale", help="an inversion at 250k-1M state dofs, and the sharded PCG iteration",
        description="a log-kappa inversion with PRDP against the converged run on each mesh "
        "(a fresh process each: time per optimiser step, time to the converged run's error, "
        "peak resident memory), then one Jacobi-PCG iteration on one device and spread over "
        "1, 2, 4 forced host devices (see prdp_fem.bench.scale)")
    scale.add_argument("--meshes", nargs="*", default=["square:501", "square:1001", "cube:81"],
                       metavar="KIND:N", help="square:N (unit_square(N), (N-1)^2 free dofs) "
                       "or cube:N (unit_cube(N), (N-1)^3); none: skip the inversions")
    scale.add_argument("--steps", type=int, default=100, help="L-BFGS steps per run")
    scale.add_argument("--sharded-n", type=int, default=501,
                       help="unit-square cells per side of the sharded PCG (0: skip it)")
    scale.add_argument("--devices", type=int, nargs="+", default=[1, 2, 4],
                       help="device counts to spread the sharded PCG over")
    scale.add_argument("--iterations", type=int, default=50,
                       help="PCG iterations per timed solve")
    scale.add_argument("--repeats", type=int, default=5,
                       help="alternated timings of the sharded PCG (the median is reported)")
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


# --------------------------------------------------------------------------------------
# commands
# --------------------------------------------------------------------------------------


#: What ``bench prdp`` writes at the top of its output directory, besides the studies.


COMMANDS = {"study": study_command, "invert": invert_command, "evaluate": evaluate_command,
            "solve": solve_command,
            "mesh-info": mesh_info_command, "mesh": mesh_info_command,
            "scenes": scenes_command, "forward": forward_command, "bench": bench_command,
            "stability": stability_command}


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
    except Interrupted as message:
        print(f"prdp-fem: {message}", file=sys.stderr)
        return 130
    except (KeyboardInterrupt, Exception) as error:  # the last guard: never a traceback
        if is_interrupt(error):
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
