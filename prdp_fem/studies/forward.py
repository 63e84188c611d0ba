"""Forward convergence studies: error of the truncated PCG solve against K and run time.

One compiled solve serves every K (implicit mode traces K), so the sweep measures solve time,
not compilation; the compile time of the first solve is reported separately. Errors are taken
against a pyamg smoothed-aggregation solve to ``rtol = 1e-12`` of the same system.

Scenes are small named recipes (mesh, element, coefficient, source, boundary data) built only
when asked for.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._xla_options import solver_options
from ..errors import SceneError, SolverConfigError
from ..fem.discretization import Discretization, discretize
from ..fem.reference import amg_solve
from ..linalg.cg import TruncatedCG, solve
from ..linalg.operator import SparseMatrix
from ..mesh.generators import l_shape, rectangle_with_hole, unit_cube, unit_square
from ..mesh.io import load_mesh

__all__ = ["SCENES", "ForwardRecord", "ForwardStudy", "build_scene", "forward_convergence"]


class ForwardRecord(NamedTuple):
    """One K of a forward study."""

    requested_iterations: int
    iterations: int
    wall_time_s: float
    relative_l2_error: float
    relative_energy_error: float
    residual_norm: float


class ForwardStudy(NamedTuple):
    n_dofs: int
    setup_time_s: float  # discretisation + reference solve
    compile_time_s: float  # first solve minus a steady solve
    records: list[ForwardRecord]


class Scene(NamedTuple):
    disc: Discretization
    kappa: np.ndarray
    source: np.ndarray


def _smooth_kappa(x):
    return 1.0 + 0.5 * np.sin(2 * np.pi * x[0]) * np.cos(np.pi * x[1])


def _bump_source(x):
    return 10.0 * np.exp(-20.0 * ((x[0] - 0.3) ** 2 + (x[1] - 0.6) ** 2))


def _scene(mesh, element: str, dirichlet) -> Scene:
    disc = discretize(mesh, element=element, kappa_space="P0", dirichlet=dirichlet)
    return Scene(disc, disc.interpolate_kappa(_smooth_kappa), disc.interpolate(_bump_source))


SCENES: dict[str, Callable[[int, str], Scene]] = {
    "square": lambda n, el: _scene(unit_square(n), el, 0.0),
    "hole": lambda n, el: _scene(rectangle_with_hole(n), el, {"left": 0.0, "hole": 1.0}),
    # l_shape(r) has 2^(r+1) cells across its side of length 2: r = log2(n) - 1 gives n
    "lshape": lambda n, el: _scene(l_shape(max(int(np.log2(max(n, 2))) - 1, 0)), el, 0.0),
    "cube": lambda n, el: _scene(unit_cube(n), el, 0.0),
}


def build_scene(name: str | None = None, *, n: int = 64, element: str = "P1",
                mesh_path: str | None = None) -> Scene:
    """A named built-in scene, or the default problem on a user's mesh file."""
    if mesh_path is not None:
        return _scene(load_mesh(mesh_path), element, 0.0)
    if name not in SCENES:
        raise SceneError(f"scene {name!r}: expected one of {sorted(SCENES)}")
    return SCENES[name](n, element)


def forward_convergence(scene: Scene, iterations: Sequence[int], *,
                        preconditioner: Any = "jacobi",
                        on_record: Callable[[ForwardRecord], None] | None = None) -> ForwardStudy:
    """Solve ``scene`` with K PCG iterations for each K; errors against pyamg.

    ``preconditioner``: a name or an object such as :func:`~prdp_fem.linalg.amg_preconditioner`'s.
    """
    bad = [k for k in iterations if isinstance(k, bool) or not isinstance(k, int | np.integer)
           or k < 0]
    if bad:
        raise SolverConfigError(f"iterations={list(iterations)!r}: expected integers >= 0 "
                                f"(first bad: {bad[0]!r})")
    TruncatedCG(0, preconditioner)  # checks the preconditioner before any setup
    start = time.perf_counter()
    disc = scene.disc
    A_ref, b_ref = disc.host_system_at(scene.kappa, scene.source)  # no map kappa -> A
    x_ref = amg_solve(A_ref, b_ref, rtol=1e-12).x
    energy_ref = np.sqrt(x_ref @ (A_ref @ x_ref))
    mass_free = disc.source_matrix[:, disc.free_dofs]
    l2_ref = np.sqrt(x_ref @ (mass_free @ x_ref))
    op, b = SparseMatrix.from_scipy(A_ref), jnp.asarray(b_ref)
    setup = time.perf_counter() - start

    @partial(jax.jit, compiler_options=solver_options(preconditioner))
    def run(op, b, k):
        return solve(op, b, TruncatedCG(k, preconditioner, gradient="implicit"))

    first = time.perf_counter()
    jax.block_until_ready(run(op, b, 1))
    first = time.perf_counter() - first
    steady = time.perf_counter()
    jax.block_until_ready(run(op, b, 1))
    compile_time = max(first - (time.perf_counter() - steady), 0.0)

    records = []
    for k in iterations:
        tic = time.perf_counter()
        sol = jax.block_until_ready(run(op, b, int(k)))
        elapsed = time.perf_counter() - tic
        error = np.asarray(sol.x) - x_ref
        record = ForwardRecord(
            requested_iterations=int(k), iterations=int(sol.iterations), wall_time_s=elapsed,
            relative_l2_error=float(np.sqrt(error @ (mass_free @ error)) / l2_ref),
            relative_energy_error=float(np.sqrt(error @ (A_ref @ error)) / energy_ref),
            residual_norm=float(sol.residual_norm))
        records.append(record)
        if on_record is not None:
            on_record(record)
    return ForwardStudy(disc.n_free, setup, compile_time, records)
