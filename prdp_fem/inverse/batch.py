r"""Many inverse problems in one program: :func:`invert_batch`.

A batch is a list of :class:`~prdp_fem.inverse.driver.InverseProblem` s of one structure --
the same mesh, unknown, observation layout and regulariser -- that differ in their arrays:
data sets (noise draws, other sources), sensor values, known coefficients, regularisation
weights. :func:`invert_batch` runs :func:`~prdp_fem.inverse.driver.invert`'s own step
(:func:`~prdp_fem.inverse.driver.make_step`) under ``jax.vmap`` (or ``jax.lax.map``, below):
one compiled program advances every member by one optimiser step, each with its own CG
iteration count.

* **Per-member K** (default): every member has its own refinement controller, fed its own
  loss (or gradient norm), so under PRDP each member refines when *its* progress stalls.
  ``K`` is a traced argument of the truncated solve, so members with different ``K`` share
  the program; a batched ``while_loop`` runs until its last member is done, the others
  masked, so a step costs what its largest ``K`` costs.
* **Shared K** (``shared_refinement=True``): one controller fed the batch's total loss (or
  the norm of all the gradients together), one ``K`` for all.

``mode="map"`` runs the members in turn inside the one program (``jax.lax.map``) instead:
each member's loops run its own ``K`` and its reductions are :func:`invert`'s (measured:
identical results over 20 L-BFGS steps of 128 members; XLA may still fuse a loop body
otherwise, so bit-for-bit equality is not promised), at about the throughput of ``vmap`` on
a CPU (``prdp-fem bench batch``); ``vmap`` is the mode for accelerators.

Arrays that are equal in every member (the stiffness map, the mass matrices: everything a
noise-seed batch shares) enter the program once, unbatched; only the arrays that differ are
stacked. Under ``vmap`` the members' results equal those of looping :func:`invert` over them
to round-off: the batched reductions sum in another order, a difference of 1e-16 that the
optimisation then carries like any perturbation (1e-13 after 15 L-BFGS steps of a log-kappa
problem; up to 1e-7 after 20 steps of a source problem at alpha = 1e-6, whose line searches
take other branches).

Counts: each member's records carry the CG iterations of its own evaluations; the
:class:`BatchInversion` totals add those an optimiser's own searches ran, which a batched
host call counts for the whole batch. Times are the batch's (one clock for all members).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optax.tree_utils as otu

from .._checks import host_values, real_array
from .._executables import SharedCompile, kept_programs
from ..errors import ShapeError, SolverConfigError
from ..linalg.amg import AMGCycle, RebuiltAMG
from ..linalg.cg import IterationCounter, TruncatedCG
from .driver import (
    InverseProblem,
    Inversion,
    InversionError,
    StepScalars,
    default_optimizer,
    initial_params,
    make_step,
)
from .history import History, StepRecord
from .refinement import Refinement, RefinementState, prdp, refuse_learning_rate_scaling
from .steps import (
    cycle_argument,
    keeps_program,
    preconditioner_key,
    step_scan_length,
    uses_stored_value,
)

__all__ = ["MODES", "BatchInversion", "invert_batch"]

#: how the members run inside the one program: together (vmap) or in turn (lax.map)
MODES = ("vmap", "map")


class BatchInversion(NamedTuple):
    """What :func:`invert_batch` returns (members in the order given)."""

    params: jax.Array                          # (members, n): the optimisation vectors
    fields: jax.Array                          # (members, n): the recovered fields
    refinements: tuple[RefinementState, ...]   # each member's controller (one, shared K)
    optimizer_state: Any                       # batched: a leading member axis on each leaf
    histories: tuple[History, ...]             # each member's records
    primal_iterations: int                     # every primal CG iteration run, all members
    adjoint_iterations: int                    # every adjoint CG iteration run, all members
    time: float                                # the batch's run time, compilation excluded
    compile_time: float

    @property
    def size(self) -> int:
        return int(self.params.shape[0])

    def member(self, i: int) -> Inversion:
        """Member ``i`` as :func:`~prdp_fem.inverse.driver.invert` would return it."""
        refinement = self.refinements[i if len(self.refinements) > 1 else 0]
        return Inversion(self.params[i], self.fields[i], refinement,
                         jax.tree.map(lambda leaf: leaf[i], self.optimizer_state),
                         self.histories[i])


class _Layout(NamedTuple):
    """How a batch enters the program: the problems' one tree structure, which leaves are
    stacked along a member axis (``True``) and which are shared."""

    treedef: Any
    stacked: tuple[bool, ...]


def _layout(problems: Sequence[InverseProblem]) -> tuple[_Layout, list, list]:
    """The batch's layout, the stacked leaves (one array per stacked position) and the
    shared ones; a :class:`ShapeError` naming the first member that does not fit."""
    first_leaves, treedef = jax.tree_util.tree_flatten(problems[0])
    paths = [jax.tree_util.keystr(path) for path, _ in
             jax.tree_util.tree_flatten_with_path(problems[0])[0]]
    members = [first_leaves]
    for i, problem in enumerate(problems[1:], start=1):
        leaves, other = jax.tree_util.tree_flatten(problem)
        if other != treedef:
            raise ShapeError(f"problems[{i}]: a problem of another structure than problems[0] "
                             "(mesh, unknown, observation layout or regulariser); expected "
                             "members that differ only in their arrays")
        for path, leaf, reference in zip(paths, leaves, first_leaves, strict=True):
            if np.shape(leaf) != np.shape(reference) or _dtype(leaf) != _dtype(reference):
                raise ShapeError(
                    f"problems[{i}]{path}: shape {np.shape(leaf)}, dtype {_dtype(leaf)}; "
                    f"expected {np.shape(reference)}, {_dtype(reference)} as in problems[0]")
        members.append(leaves)
    stacked, batched, shared = [], [], []
    for position, reference in enumerate(first_leaves):
        column = [leaves[position] for leaves in members]
        same = all(leaf is reference for leaf in column[1:])
        if not same:  # equal values in other arrays are shared too
            host = np.asarray(reference)
            same = all(leaf is reference or np.array_equal(np.asarray(leaf), host)
                       for leaf in column[1:])
        stacked.append(not same)
        if same:
            shared.append(reference)
        else:
            batched.append(np.stack([np.asarray(leaf) for leaf in column]))
    return _Layout(treedef, tuple(stacked)), jax.device_put(batched), shared


def _dtype(leaf) -> np.dtype:
    return leaf.dtype if hasattr(leaf, "dtype") else np.asarray(leaf).dtype


def _merged(layout: _Layout, stacked: list, shared: list) -> list:
    stacked_leaves, shared_leaves = iter(stacked), iter(shared)
    return [next(stacked_leaves) if is_stacked else next(shared_leaves)
            for is_stacked in layout.stacked]


def _new_batched_program(optimizer, gradient, tolerance_mode, preconditioner,
                         layout: _Layout, mode: str) -> SharedCompile:
    step = make_step(optimizer, gradient, tolerance_mode, preconditioner)

    def batched(stacked, shared, counter, z, opt_state, scan_length, K, K_adj, rtol,
                *cycle):
        def member(stacked, z, opt_state, K, K_adj, rtol):
            problem = layout.treedef.unflatten(_merged(layout, stacked, shared))
            z_next, opt_state, _, packed = step(problem, counter, z, opt_state, None,
                                                scan_length, K, K_adj, rtol, *cycle)
            return z_next, opt_state, packed

        members = (stacked, z, opt_state, K, K_adj, rtol)
        if mode == "map":
            return jax.lax.map(lambda arguments: member(*arguments), members)
        return jax.vmap(member)(*members)

    return SharedCompile(batched, static_argnum=5)


#: The compiled batched step per settings and layout, kept as :func:`invert`'s step is.
_batched_program = kept_programs(_new_batched_program)


def invert_batch(problems: Sequence[InverseProblem], *,
                 optimizer: optax.GradientTransformation | None = None,
                 refinement: Refinement | None = None, gradient: str = "implicit",
                 steps: int = 100, init: np.ndarray | None = None,
                 preconditioner: Any = "jacobi", monitor: str | None = None,
                 shared_refinement: bool = False, mode: str = "vmap") -> BatchInversion:
    """Minimise each member's ``J`` for ``steps`` optimiser steps in one compiled program.

    Parameters
    ----------
    problems
        Problems of one structure (see the module's text); at least one.
    optimizer, refinement, gradient, steps, preconditioner
        As for :func:`~prdp_fem.inverse.driver.invert`. The preconditioner is one for the
        whole batch: ``"jacobi"`` (each member's own diagonal), ``"identity"`` or a fixed
        AMG cycle; a :class:`~prdp_fem.linalg.RebuiltAMG` is refused.
    init
        Initial field: ``None`` (as :func:`invert`), one field for every member (``(n,)``)
        or one per member (``(members, n)``).
    monitor
        ``"loss"`` or ``"gradient"`` (default: what the controller asks for, else the loss).
    shared_refinement
        One controller and one ``K`` for the batch, fed the total loss (or the norm of all
        gradients), instead of one per member.
    mode
        ``"vmap"``: the members computed together (``jax.vmap``; what an accelerator wants;
        equal to looping :func:`invert` to round-off, see the module's text). ``"map"``: the
        members one after another inside the one program (``jax.lax.map``), each member's
        loops running its own ``K``, its reductions summed as :func:`invert` sums them.

    Raises
    ------
    ShapeError
        Members of different structure or array shapes, or ``init`` of the wrong shape.
    SolverConfigError
        Bad options (as :func:`invert`), an empty batch or a per-member preconditioner.
    InversionError
        A member's step produced non-finite parameters (names the member and the step).
    """
    problems = _checked_problems(problems)
    refinement = prdp() if refinement is None else refinement
    monitor = _checked_options(refinement, gradient, steps, preconditioner, monitor,
                               shared_refinement)
    if mode not in MODES:
        raise SolverConfigError(f"mode={mode!r}: expected one of {list(MODES)}")
    given = default_optimizer() if optimizer is None else optimizer
    optimizer = optax.with_extra_args_support(given)
    members = len(problems)
    layout, stacked, shared = _layout(problems)  # refuses members that do not fit first
    z = jax.device_put(np.stack([np.asarray(initial_params(problem, start)) for
                                 problem, start in zip(problems, _starts(init, problems),
                                                       strict=True)]))
    opt_state = jax.vmap(optimizer.init)(z)
    key = preconditioner_key(preconditioner)
    program = _batched_program(given, gradient, refinement.tolerance_mode, key, layout, mode,
                               keep=keeps_program(key))
    compiled_before = program.seconds
    controls = [refinement.init() for _ in range(1 if shared_refinement else members)]
    counter = IterationCounter()
    histories = [History() for _ in range(members)]
    returned = np.zeros((members, 3))  # per member: primal, adjoint iterations, solves
    failed_steps = np.zeros(members, dtype=int)
    run_time = 0.0
    settings = _member_settings(controls, members)
    arguments = _device_settings(settings)
    for k in range(1, steps + 1):
        start = time.perf_counter()
        compile_before = program.seconds
        z, opt_state, packed = program(
            stacked, shared, counter, z, opt_state,
            step_scan_length(gradient, max(K for K, _, _ in settings)), *arguments,
            *cycle_argument(preconditioner))
        scalars = [StepScalars(*row) for row in np.asarray(packed).tolist()]
        _check_finite(scalars, k, settings)
        failed = np.array([bool(s.failed) for s in scalars])
        failed_steps += failed
        controls = _updated(refinement, controls, scalars, failed, monitor)
        previous, settings = settings, _member_settings(controls, members)
        refined = np.array([new != old for new, old in zip(settings, previous, strict=True)])
        if refined.any():
            arguments = _device_settings(settings)
            # as invert does: the stored value belongs to the old solver
            if uses_stored_value(opt_state):
                stored = otu.tree_get(opt_state, "value")
                opt_state = otu.tree_set(opt_state, value=jnp.where(refined, jnp.inf, stored))
        run_time += time.perf_counter() - start - (program.seconds - compile_before)
        for i, (scalar, (K_i, K_adj_i, rtol_i)) in enumerate(zip(scalars, previous,
                                                                   strict=True)):
            returned[i] += (scalar.primal, scalar.adjoint, scalar.primal_solves)
            control = controls[0 if shared_refinement else i]
            histories[i] = histories[i].append(StepRecord(
                step=k, iterations=K_i, adjoint_iterations=K_adj_i, rtol=rtol_i,
                refinements=int(control.refinements), primal_iterations=int(returned[i, 0]),
                adjoint_iterations_total=int(returned[i, 1]), validation_iterations=0,
                evaluations=int(returned[i, 2]), time=run_time,
                compile_time=program.seconds - compiled_before, loss=scalar.value,
                misfit=scalar.misfit, parameter_error=scalar.parameter_error,
                state_error=math.nan, failed_steps=int(failed_steps[i]), rebuilds=0))
    fields = jax.vmap(problems[0].parameterization.field)(z)
    return BatchInversion(
        z, fields, tuple(controls), opt_state, tuple(histories),
        primal_iterations=counter.primal + int(returned[:, 0].sum()),
        adjoint_iterations=counter.adjoint + int(returned[:, 1].sum()),
        time=run_time, compile_time=program.seconds - compiled_before)


def _checked_problems(problems) -> list[InverseProblem]:
    if isinstance(problems, InverseProblem) or not isinstance(problems, Sequence):
        raise SolverConfigError(f"problems={type(problems).__name__}: expected a sequence of "
                                "InverseProblem (a batch)")
    problems = list(problems)
    if not problems:
        raise SolverConfigError("problems: an empty batch; expected at least one problem")
    for i, problem in enumerate(problems):
        if not isinstance(problem, InverseProblem):
            raise SolverConfigError(f"problems[{i}]: a {type(problem).__name__}; expected an "
                                    "InverseProblem")
    return problems


def _checked_options(refinement, gradient, steps, preconditioner, monitor,
                     shared_refinement) -> str:
    """The run's monitor, after refusing what :func:`invert_batch` does not run."""
    if gradient not in ("implicit", "unrolled"):
        raise SolverConfigError(f"gradient={gradient!r}: expected 'implicit' or 'unrolled'")
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or steps < 0:
        raise SolverConfigError(f"steps={steps!r}: expected an integer >= 0")
    if not isinstance(refinement, Refinement):
        raise SolverConfigError(f"refinement={refinement!r}: expected a controller from "
                                "prdp_fem.inverse.refinement (prdp(), fixed(K) or converged(rtol))")
    refuse_learning_rate_scaling(refinement, "a batched inversion")
    if refinement.tolerance_mode and gradient == "unrolled":
        raise SolverConfigError("a tolerance-mode controller needs gradient='implicit' (reverse "
                                "mode cannot run through a loop of unknown length)")
    if isinstance(preconditioner, RebuiltAMG) or not (
            isinstance(preconditioner, str | AMGCycle)):
        raise SolverConfigError(
            f"preconditioner={type(preconditioner).__name__}: expected 'jacobi', 'identity' or "
            "a fixed AMGCycle shared by the batch (invert() rebuilds a member's own AMG)")
    TruncatedCG(0, preconditioner)  # checks the name
    if not isinstance(shared_refinement, bool):
        raise SolverConfigError(f"shared_refinement={shared_refinement!r}: expected True or "
                                "False")
    wanted = getattr(refinement, "monitor", None)
    chosen = monitor if monitor is not None else (wanted or "loss")
    if chosen not in ("loss", "gradient") or (wanted is not None and chosen != wanted):
        raise SolverConfigError(f"monitor={monitor!r}: expected 'loss' or 'gradient'"
                                + (f" (this controller is fed the {wanted!r})" if wanted else ""))
    return chosen


def _starts(init, problems: list[InverseProblem]) -> list:
    """One initial field (or ``None``) per member."""
    if init is None:
        return [None] * len(problems)
    n = problems[0].n_parameters
    values = real_array(host_values(init, "init (initial fields)"), "init (initial fields)")
    if values.ndim <= 1:  # one field for all: initial_params checks it as invert does
        return [values] * len(problems)
    if values.shape != (len(problems), n):
        raise ShapeError(f"init: shape {values.shape}; expected ({n},) for every member or "
                         f"({len(problems)}, {n}), one field per member")
    return list(values)


def _member_settings(controls: list, members: int) -> list[tuple[int, int, float]]:
    """``(K, K_adj, rtol)`` of every member (one shared controller: the same for all)."""
    settings = [control.settings() for control in controls]
    return settings * members if len(settings) == 1 else settings


def _device_settings(settings: list[tuple[int, int, float]]) -> tuple[jax.Array, ...]:
    """``(K, K_adj, rtol)`` of every member, one vector each."""
    K, K_adj, rtol = zip(*settings, strict=True)
    return tuple(jax.device_put((np.asarray(K, np.int32), np.asarray(K_adj, np.int32),
                                 np.asarray(rtol, np.float64))))


def _check_finite(scalars: list[StepScalars], k: int, settings) -> None:
    for i, s in enumerate(scalars):
        if not (math.isfinite(s.value) and math.isfinite(s.grad_norm) and s.finite_params):
            K, K_adj, rtol = settings[i]
            raise InversionError(
                f"member {i}, step {k}: non-finite loss, gradient or parameters (loss "
                f"{s.value!r}, gradient norm {s.grad_norm!r}, K={K}, K_adj={K_adj}, "
                f"rtol={rtol!r}); try a smaller step, more CG iterations or another gradient "
                "mode")


def _updated(refinement: Refinement, controls: list, scalars: list[StepScalars],
             failed: np.ndarray, monitor: str) -> list:
    """Each controller after the step: a member's own value, or the batch's total."""
    values = [s.grad_norm if monitor == "gradient" else s.value for s in scalars]
    if len(controls) == 1 and len(scalars) > 1:  # shared: the batch's objective
        total = math.sqrt(sum(v * v for v in values)) if monitor == "gradient" \
            else math.fsum(values)
        return [refinement.update(controls[0], total, bool(failed.any()))]
    return [refinement.update(control, value, bool(fail))
            for control, value, fail in zip(controls, values, failed, strict=True)]
