"""The mixed setup: an emulator trained through the fine solver (the PRDP paper's heat chain)."""

import dataclasses
import itertools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.sparse.linalg as spla
from conftest import small_heat_case

import prdp_fem as pf
from prdp_fem.errors import SolverConfigError
from prdp_fem.inverse import converged, prdp, truncation_gap
from prdp_fem.learning import Model, heat, learned
from prdp_fem.scene import SceneError, load_scene, parse_scene
from prdp_fem.scene.build import build_heat, heat_train_options
from prdp_fem.studies import run_study
from prdp_fem.studies.evaluation import evaluate_study
from prdp_fem.studies.runner import ResultsLog

SCENES = Path(__file__).resolve().parent.parent / "examples" / "scenes"

DT, SUBSTEPS = 0.02, 4


@pytest.fixture(scope="module")
def small():
    """The 25-dof heat case, its reference data (4 substeps of dt / 4) and the fine problem."""
    disc, _, trajectories, validation = small_heat_case(DT)
    return disc, heat.heat_problem(disc, DT / SUBSTEPS), trajectories, validation


def _exact_increment(params, u):
    return params @ u


def exact_emulator(disc, problem):
    """The reference's step as a linear model: u + W u with W = F^4 - I, F the fine step's
    matrix (dense, 25 dofs); homogeneous, as the emulator's scaling assumes."""
    fine = spla.spsolve(problem.matrix.to_scipy().tocsc(), problem.mass.to_scipy().toarray())
    step = np.linalg.matrix_power(fine, SUBSTEPS)
    return Model(_exact_increment, jnp.asarray(step - np.eye(problem.n_free)))


def chain_loss(network, problem, batch, solver, substeps=SUBSTEPS):
    return heat.batch_loss(network, problem, batch, solver, setup="mixed", mode="wig",
                           substeps=substeps)


# one program per solver (run op by op, the batched chain compiles some 200 small programs)
jitted_chain_loss = jax.jit(chain_loss, static_argnames=("solver", "substeps"))

# the emulator's rollout alone (the mixed setup's validation), one program per shape
emulator_rollout_error = jax.jit(lambda network, problem, trajectories: heat.rollout_error(
    network, problem, trajectories, None, setup="prediction"))

# one optimiser object and one network width for the trainings of this module: their steps
# are one kept program (kept per optimiser object and shapes), compiled once, not per test
ADAM, HIDDEN = optax.adam(3e-3), (32,)


def test_the_exact_emulator_has_zero_mixed_loss_only_with_converged_solves(small):
    """The chain is the reference's own scheme: the exact step (network) followed by converged
    fine steps reproduces the data to round-off; truncated solves do not (their error is what
    a truncated run trains against), and a chain of coarse steps of dt would not either."""
    disc, problem, trajectories, _ = small
    # windows of 2 steps: the network's step, then one solver step of SUBSTEPS solves (a
    # chain of 3 compiles twice the solves into each of the three programs)
    batch = heat.windows(trajectories, 2)[:8]
    emulator = exact_emulator(disc, problem)
    loss, iterations = jitted_chain_loss(emulator, problem, batch,
                                         solver=pf.ConvergedCG(rtol=1e-13))
    assert float(loss) < 1e-20 and int(iterations) > 0
    truncated, few = jitted_chain_loss(emulator, problem, batch, solver=pf.TruncatedCG(1))
    assert float(truncated) > 1e-8 and int(few) == 8 * SUBSTEPS  # 1 solver step of 4
    coarse = heat.heat_problem(disc, DT)
    wrong = jitted_chain_loss(emulator, coarse, batch, solver=pf.ConvergedCG(rtol=1e-13),
                              substeps=1)[0]
    assert float(wrong) > 1e-8


@pytest.mark.parametrize("solver", [
    pytest.param(pf.TruncatedCG(3, gradient="unrolled"), marks=pytest.mark.slow),  # 13 s
    pf.ConvergedCG(rtol=1e-13)], ids=["unrolled-K3", "converged"])
def test_the_mixed_gradient_passes_a_taylor_test_and_flows_through_the_solver(small, solver):
    _, problem, trajectories, _ = small
    network = learned.mlp_init(jax.random.PRNGKey(0), [problem.n_free, 16, problem.n_free],
                               output_scale=0.3)
    # windows of 2 steps: the network's step, then one solver step (of SUBSTEPS solves) that
    # the gradient flows through; a chain of 3 compiles twice the solves and their adjoints
    batch = heat.windows(trajectories, 2)[:4]

    def loss(layers):
        return chain_loss(network._replace(layers=layers), problem, batch, solver)[0]

    # the loss and its gradient in one program, which the Taylor test evaluates too (a
    # separately jitted loss would compile the solves once more)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    gradient = value_and_grad(network.layers)[1]
    result = pf.taylor_test(lambda layers: value_and_grad(layers)[0], network.layers,
                            gradient=gradient, h0=1e-2)
    assert result.passed(), result.rates

    def first_step_only(layers):  # the one-step term alone: what a chain without solver gives
        net = network._replace(layers=layers)
        s = jax.vmap(lambda w: heat.stepper("prediction", net, problem, w[0], solver)[0])(batch)
        e = s - batch[:, 1]
        return jnp.mean(jax.vmap(lambda x, t: jnp.vdot(x, problem.mass(x))
                                 / jnp.vdot(t, problem.mass(t)))(e, batch[:, 1])) / 2

    alone = jax.jit(jax.grad(first_step_only))(network.layers)
    difference = optax.tree.norm(jax.tree_util.tree_map(jnp.subtract, gradient, alone))
    assert float(difference) > 0.1 * float(optax.tree.norm(gradient))


def test_the_steps_adjoint_tally_equals_a_host_counters_count_in_tolerance_mode(small):
    """A training step counts its adjoint solves in its own program (the gradient with respect
    to a tally seed): one step over all 60 windows at rtol 1e-3 counts what a host counter
    counts for the same loss's gradient at the same parameters: each window's 4 adjoint
    solves, summed over the batch under ``vmap``."""
    _, problem, trajectories, validation = small
    network = jax.tree.map(np.asarray,
                           heat.initial_network(problem, trajectories, "mixed", HIDDEN, seed=0))
    batch = heat.windows(trajectories, 2)
    training = heat.train(problem, network, trajectories, validation, setup="mixed",
                          mode="wig", unroll=2, optimizer=ADAM, epochs=1,
                          batch_size=batch.shape[0], substeps=SUBSTEPS,
                          refinement=converged(1e-3))
    [record] = training.records
    host = pf.IterationCounter()

    @jax.jit
    def gradient(params, rtol):  # rtol traced, as in the step
        solver = pf.ConvergedCG(rtol=rtol, max_iterations=record.iterations,
                                preconditioner="jacobi")
        return jax.grad(lambda p: heat.batch_loss(
            network.replace_params(p), problem, batch, solver, setup="mixed", mode="wig",
            substeps=SUBSTEPS, step=lambda *a: heat.heat_step(*a, counter=host))[0])(params)

    jax.block_until_ready(gradient(network.params, jnp.float64(1e-3)))
    jax.effects_barrier()
    assert host.adjoint_solves == batch.shape[0] * SUBSTEPS
    assert record.adjoint_iterations_total == host.adjoint > host.adjoint_solves
    assert record.primal_iterations == host.primal


def test_mixed_training_validates_the_emulator_alone_and_prdp_saves_iterations(small):
    """PRDP and converged mixed runs: the validation rollouts run no solver (the emulator
    alone, equal to the prediction setup's rollout error), both runs lower it, and the PRDP
    run's solves cost fewer CG iterations while ending within 2 % of the converged run."""
    _, problem, trajectories, validation = small
    # the scales as float64 arrays, as the trained networks hold them: one rollout program
    network = jax.tree.map(np.asarray,
                           heat.initial_network(problem, trajectories, "mixed", HIDDEN, seed=0))
    start = emulator_rollout_error(network, problem, validation)[0]
    # windows of 2 steps: one solver step a window, half the step program of a chain of 3
    # (whose compilation is half the test); measured: both runs end at 0.41 of the start, the
    # PRDP run's solves cost 0.14 (primal) and 0.19 (adjoint) of the converged run's, 0.3 %
    # apart
    options = dict(setup="mixed", mode="wig", unroll=2, optimizer=ADAM,
                   epochs=20, batch_size=12, substeps=SUBSTEPS, seed=1)
    runs = {name: heat.train(problem, network, trajectories, validation, refinement=control,
                             **options)
            for name, control in (("prdp", prdp(rtol=1e-2, rtol_factor=0.1, rtol_min=1e-10)),
                                  ("converged", converged(1e-10)))}
    for training in runs.values():
        last = training.records[-1]
        assert last.validation_iterations == 0
        assert last.validation_error < 0.5 * float(start)
        again = emulator_rollout_error(training.network, problem, validation)[0]
        assert last.validation_error == pytest.approx(float(again), rel=1e-12)
    truncated, exact = runs["prdp"].records[-1], runs["converged"].records[-1]
    assert truncated.primal_iterations < 0.7 * exact.primal_iterations
    assert truncated.adjoint_iterations_total < 0.7 * exact.adjoint_iterations_total
    assert truncated.adjoint_iterations_total > 0
    assert abs(truncated.validation_error / exact.validation_error - 1) < 0.02


def _gap_windows(validation, unroll):
    """The validation windows the mixed gap is measured on: starts every ``unroll`` steps."""
    states = np.asarray(validation.states)
    starts = range(0, validation.steps - unroll + 1, unroll)
    return jnp.asarray(np.concatenate([states[:, t:t + unroll + 1] for t in starts]))


# the test's own chain program (not the trainer's), the tolerance traced: one compile for all
_chains_at = jax.jit(lambda network, problem, windows, rtol: jax.vmap(
    lambda w: heat.chain_states(network, problem, w,
                                pf.ConvergedCG(rtol=rtol, max_iterations=100_000),
                                substeps=SUBSTEPS))(windows))


def _mass_norm2(problem):
    """``norm2(e, t)``: the sum over windows and steps of ``||e||_M^2 / ||t||_M^2``, with
    SciPy's mass matrix."""
    mass = problem.mass.to_scipy()

    def norm2(e, t):
        e, t = np.asarray(e).reshape(-1, e.shape[-1]), np.asarray(t).reshape(-1, t.shape[-1])
        return sum((a @ mass @ a) / (b @ mass @ b) for a, b in zip(e, t, strict=True))

    return norm2


def test_the_mixed_gap_bounds_the_chain_error_change_on_non_overlapping_validation_windows(small):
    """A truncation_gap() controller on a mixed run is fed the chain gap over the validation
    windows starting every ``unroll`` steps (recomputed here from the trained network's chain
    states, at the level and at the reference tolerance ``rtol * reference_factor``), which
    is the gap against converged chains to about ``reference_factor`` of itself and bounds
    the change of the chain's error; it tightens the solves exactly when the gap exceeds
    ``max_gap`` and counts both passes' CG iterations with the validation's."""
    _, problem, trajectories, validation = small
    # the width and optimiser of the mixed training test: its step program, compiled once;
    # measured gaps 0.0140, 0.0141, 0.0161, 0.0018: the third epoch tightens, no other
    network = jax.tree.map(np.asarray,
                           heat.initial_network(problem, trajectories, "mixed", HIDDEN, seed=0))
    unroll, max_gap, factor = 2, 0.015, 1e-2
    training = heat.train(problem, network, trajectories, validation, setup="mixed",
                          mode="wig", unroll=unroll, optimizer=ADAM, epochs=4,
                          batch_size=12, substeps=SUBSTEPS, seed=1,
                          refinement=truncation_gap(1e-2, max_gap=max_gap, redo=False,
                                                    reference_factor=factor))
    records = training.records
    gap_windows = _gap_windows(validation, unroll)  # 4 trajectories of 6 steps: starts 0, 2, 4
    assert gap_windows.shape[0] == 12
    last = records[-1]
    chains = {rtol: _chains_at(training.network, problem, gap_windows, rtol)
              for rtol in (1e-10, last.rtol * factor, last.rtol)}
    (converged_states, _), (reference, reference_its), (truncated, truncated_its) = (
        chains[1e-10], chains[last.rtol * factor], chains[last.rtol])
    truth = gap_windows[:, 1:]
    norm2 = _mass_norm2(problem)

    def gap_against(states):
        return np.sqrt(norm2(truncated - states, truth) / norm2(states - truth, truth))

    assert last.truncation_gap == pytest.approx(gap_against(reference), rel=1e-6)
    converged_gap = gap_against(converged_states)  # the reference's error: ~factor of it
    assert last.truncation_gap == pytest.approx(converged_gap, rel=3 * factor)
    loss_t, loss_c = norm2(truncated - truth, truth), norm2(converged_states - truth, truth)
    assert abs(np.sqrt(loss_t / loss_c) - 1) <= converged_gap  # the bound it claims
    # the emulator's rollouts run no solver: the validation count is the two chain passes
    assert last.validation_iterations - records[-2].validation_iterations == \
        int(np.sum(reference_its)) + int(np.sum(truncated_its))
    tightened = [b.rtol < a.rtol for a, b in itertools.pairwise(records)]
    assert tightened == [a.truncation_gap > max_gap for a in records[:-1]]
    assert any(tightened) and not all(tightened)


def test_the_mixed_gap_s_first_level_refers_every_level_to_its_own_reference(small):
    """Before epoch 1 the untrained emulator's gap is measured at each level the controller
    tries, against a reference chain at that level times ``reference_factor``: the first
    level and the CG iterations of those passes, recomputed here level by level."""
    _, problem, trajectories, validation = small
    network = jax.tree.map(np.asarray,
                           heat.initial_network(problem, trajectories, "mixed", HIDDEN, seed=0))
    unroll, max_gap, factor, first = 2, 0.015, 1e-2, 0.3
    training = heat.train(problem, network, trajectories, validation, setup="mixed",
                          mode="wig", unroll=unroll, optimizer=ADAM, epochs=1,
                          batch_size=12, substeps=SUBSTEPS, seed=1,
                          refinement=truncation_gap(first, max_gap=max_gap, redo=False,
                                                    reference_factor=factor))
    gap_windows = _gap_windows(validation, unroll)
    truth = gap_windows[:, 1:]
    norm2 = _mass_norm2(problem)

    def passes(net, rtol):  # the gap at a level and the CG iterations of its two passes
        (reference, its_r), (truncated, its_t) = (
            _chains_at(net, problem, gap_windows, r) for r in (rtol * factor, rtol))
        gap = np.sqrt(norm2(truncated - reference, truth) / norm2(reference - truth, truth))
        return gap, int(np.sum(its_r)) + int(np.sum(its_t))

    rtol, iterations, levels = first, 0, []
    while True:
        gap, its = passes(network, rtol)
        iterations, levels = iterations + its, [*levels, gap]
        if gap <= max_gap:
            break
        rtol *= 0.1
    record = training.records[0]
    assert len(levels) >= 2 and record.rtol == pytest.approx(rtol, rel=1e-12), levels
    # the first level's passes, then epoch 1's two chain passes at the level it trained at
    assert record.validation_iterations == iterations + passes(training.network, rtol)[1]


def test_bad_mixed_options_are_refused(small):
    _, problem, trajectories, validation = small
    network = heat.initial_network(problem, trajectories, "mixed", (8,))
    base = dict(setup="mixed", epochs=1, batch_size=4, substeps=SUBSTEPS)
    with pytest.raises(SolverConfigError, match="mode='nog' with setup='mixed'"):
        heat.train(problem, network, trajectories, validation, mode="nog", **base)
    with pytest.raises(SolverConfigError, match="unroll=1 with setup='mixed'"):
        heat.train(problem, network, trajectories, validation, mode="wig", unroll=1, **base)
    with pytest.raises(SolverConfigError, match="substeps=0"):
        heat.train(problem, network, trajectories, validation, mode="wig",
                   **{**base, "substeps": 0})


# --------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------

TINY_MIXED = {
    "name": "tiny_mixed", "mesh": {"n": 4}, "pde": {"source": 0.0},
    "heat": {"dt": 0.02, "steps": 4, "substeps": 2, "trajectories": 6,
             "validation_trajectories": 3, "test_trajectories": 2, "hidden": [8],
             "setup": "mixed", "mode": "wig", "unroll": 2, "epochs": 3, "batch_size": 6},
    "refinement": {"kind": "prdp", "rtol": 1e-2, "rtol_min": 1e-10},
    "optimizer": {"name": "adam", "learning_rate": 3e-3},
    "study": {"runs": [{"name": "mixed prdp"},
                       {"name": "mixed converged",
                        "refinement": {"kind": "converged", "rtol": 1e-10}}]},
}


@pytest.mark.parametrize(("heat_table", "refinement", "match"), [
    ({"setup": "mixed"}, {}, r"bad.toml: heat.mode = 'nog' with heat.setup = 'mixed': "
                             r"expected 'wig'"),
    ({"setup": "mixed", "mode": "wig", "unroll": 1}, {},
     r"heat.unroll = 1 with heat.setup = 'mixed': expected at least 2"),
])
def test_bad_mixed_scenes_name_the_key_and_the_expectation(heat_table, refinement, match):
    with pytest.raises(SceneError, match=match):
        parse_scene({"name": "bad", "heat": heat_table, "refinement": refinement},
                    source="bad.toml")


def test_a_mixed_scene_takes_the_gap_kind_its_trainer_measures_on_the_chain():
    scene = parse_scene({**TINY_MIXED, "refinement": {"kind": "gap", "max_gap": 0.02}},
                        source="gap.toml")
    variant = dict(scene.runs())["mixed prdp"]
    assert variant.refinement.kind == "gap" and variant.refinement.max_gap == 0.02
    assert heat_train_options(variant, build_heat(variant).problem)["refinement"].monitor == \
        "truncation_gap"


def test_a_mixed_study_trains_through_the_fine_step_pairs_and_evaluates(tmp_path):
    scene = parse_scene(TINY_MIXED, source="mixed.toml")
    assert [n for n, _ in parse_scene({"heat": {"setup": "mixed", "mode": "wig"}}).runs()] \
        == ["converged", "scene"]  # a bare mixed scene gets its converged baseline
    variant = dict(scene.runs())["mixed prdp"]
    setup = build_heat(variant)
    options = heat_train_options(variant, setup.problem)
    assert float(setup.problem.dt) == pytest.approx(0.01) and options["substeps"] == 2
    out = tmp_path / "study"
    result = run_study(scene, out)
    epochs = [r for r in ResultsLog(out / "results.jsonl").records() if r["type"] == "epoch"]
    direct = heat.train(setup.problem, setup.network, setup.train_set, setup.validation_set,
                        test_set=setup.test_set, **options).records
    mine = [r for r in epochs if r["run"] == "mixed prdp"]
    np.testing.assert_allclose([r["test_error"] for r in mine],
                               [r.test_error for r in direct], rtol=1e-9)
    assert [r["primal_iterations"] for r in mine] == [r.primal_iterations for r in direct]
    assert all(r["validation_iterations"] == 0 for r in epochs)
    rows = {row["run"]: row for row in result.summary}
    assert rows["mixed prdp"]["converged_run"] == "mixed converged"
    assert rows["mixed prdp"]["cg_iterations"] < rows["mixed converged"]["cg_iterations"]
    last = {r["run"]: r for r in epochs}
    evaluated = {row["run"]: row for row in evaluate_study(scene, out, samples=0)}
    for run in ("mixed prdp", "mixed converged"):  # the emulator alone, from the checkpoint
        assert evaluated[run]["test_error"] == pytest.approx(last[run]["test_error"],
                                                             rel=1e-10)


def test_the_example_mixed_scene_trains_the_heat_emulators_network_through_the_solver():
    scene = load_scene(SCENES / "heat_emulator_mixed.toml")
    emulator = load_scene(SCENES / "heat_emulator.toml")
    runs = dict(scene.runs())
    assert {n: (v.heat.setup, v.heat.mode, v.refinement.kind) for n, v in runs.items()} == {
        "mixed prdp": ("mixed", "wig", "prdp"), "mixed converged": ("mixed", "wig", "converged"),
        "emulator": ("prediction", "nog", "prdp")}
    assert scene.mesh == emulator.mesh and scene.pde == emulator.pde
    for key in ("dt", "steps", "substeps", "trajectories", "validation_trajectories",
                "test_trajectories", "width", "hidden", "unroll", "epochs", "batch_size"):
        assert getattr(scene.heat, key) == getattr(emulator.heat, key), key
    # PRDP from a finer start, its stalls judged per unit learning rate (the cosine schedule)
    assert scene.refinement == dataclasses.replace(emulator.refinement, rtol=3e-3,
                                                   per_learning_rate=True)
    assert scene.optimizer == emulator.optimizer and scene.optimizer.decay == "cosine"
