"""The truncation-gap controller (refinement.truncation_gap): its rule, its checks, the
trainers that feed it (heat and learned: the gap against their own validation passes, the
extra pass counted), and the scene kind ``gap``."""

import itertools
import math
from pathlib import Path

import jax
import numpy as np
import optax
import pytest
from conftest import small_heat_case

import prdp_fem as pf
from prdp_fem.errors import SceneError, SolverConfigError
from prdp_fem.inverse import state_from_dict, state_to_dict, truncation_gap
from prdp_fem.learning import heat, learned
from prdp_fem.scene import load_scene
from prdp_fem.scene.build import controller
from prdp_fem.scene.spec import GapSpec, SceneSolverConfigError, parse_scene, with_overrides
from prdp_fem.studies.runner import ResultsLog, run_study

DT = 0.02

# one optimizer object: the trainings of equal settings below share one compiled step (kept
# per optimizer object), as a study's runs do
ADAM = optax.adam(1e-2)

# --- the rule ---------------------------------------------------------------------------


def test_a_gap_above_max_gap_divides_rtol_once_and_a_smaller_one_keeps_it():
    control = truncation_gap(1e-2, max_gap=0.05, rtol_factor=0.1, rtol_min=1e-4)
    state = control.init()
    assert control.tolerance_mode and control.monitor == "truncation_gap"
    rtols = []
    for gap in [0.01, 0.2, 0.9, 0.04, 0.06, 0.3, 0.0]:
        state = control.update(state, gap)
        rtols.append(float(state.rtol))
    # one level per value above 0.05, never below rtol_min, never loosened
    assert rtols == pytest.approx([1e-2, 1e-3, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4])
    assert int(state.refinements) == 2
    assert float(state.checkpoint) == 0.0  # the last gap fed


def test_a_non_finite_gap_refines_and_is_not_counted():
    control = truncation_gap(1e-3, max_gap=0.01)
    state = control.update(control.init(), math.nan)
    assert float(state.rtol) == pytest.approx(1e-4) and int(state.count) == 0
    state = control.update(state, math.inf)
    assert float(state.rtol) == pytest.approx(1e-5)


def test_the_state_round_trips_through_json_and_jit():
    control = truncation_gap(1e-2, max_gap=0.01)
    state = control.update(control.init(), 0.5)
    assert state_to_dict(state_from_dict(state_to_dict(state))) == state_to_dict(state)
    jitted = jax.jit(control.update)(jax.tree.map(np.asarray, control.init()), 0.5)
    assert float(jitted.rtol) == pytest.approx(float(state.rtol))


@pytest.mark.parametrize("options, match", [
    (dict(rtol=0.0), "rtol"), (dict(rtol=1e-12, rtol_min=1e-10), "rtol_min"),
    (dict(rtol_factor=1.0), "rtol_factor"), (dict(max_gap=0.0), "max_gap"),
    (dict(max_gap=math.inf), "max_gap"), (dict(max_gap=True), "max_gap"),
    (dict(redo=1), "redo"), (dict(reference_factor=1.0), "reference_factor"),
    (dict(reference_factor=0.0), "reference_factor"),
    (dict(reference_factor=True), "reference_factor"),
    (dict(max_iterations=0), "max_iterations")])
def test_bad_settings_are_refused_with_their_names(options, match):
    with pytest.raises(SolverConfigError, match=match):
        truncation_gap(**options)


def test_an_inversion_refuses_it():
    disc = pf.discretize(pf.unit_square(6), dirichlet=0.0)
    problem = pf.inverse_problem(disc, pf.full_field(disc, data=np.ones(disc.n_dofs)),
                                 unknown="source", alpha=1e-6)
    with pytest.raises(SolverConfigError, match=r"truncation_gap.*inversion cannot feed it"):
        pf.invert(problem, steps=2, refinement=truncation_gap())


# --- the trainers -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_heat():
    """6x6 P1 (25 free dofs), 12 training and 4 validation trajectories of 6 steps."""
    return small_heat_case(DT)[1:]


def heat_network(problem, hidden=16):
    """An untrained MLP whose scales are float64 arrays, as a trained network holds them: a
    gap-fed training validates the untrained network before its first step, and Python-float
    scales would compile its validation passes a second time for the trained one."""
    return jax.tree.map(np.asarray, learned.mlp_init(
        jax.random.PRNGKey(0), [problem.n_free, hidden, problem.n_free], output_scale=0.05))


# a validation rollout at a tolerance, compiled once for every rtol (run op by op, each
# rollout would compile its scan anew)
rollout_error_at = jax.jit(lambda network, problem, trajectories, rtol: heat.rollout_error(
    network, problem, trajectories, pf.ConvergedCG(rtol=rtol, max_iterations=100_000)))


def heat_gap(network, problem, validation, rtol):
    """(gap, converged iterations, iterations at rtol) of a validation rollout."""
    e_conv, its_conv = rollout_error_at(network, problem, validation, 1e-10)
    e_rtol, its_rtol = rollout_error_at(network, problem, validation, rtol)
    return abs(float(e_rtol) / float(e_conv) - 1), int(its_conv), int(its_rtol)


def test_the_first_level_is_settled_on_the_untrained_model_and_counted(small_heat):
    """Before epoch 1 the controller is fed the untrained network's gap until it stops
    tightening: the first epoch trains at the loosest level the network cannot see, and
    the passes that found it are counted with the validation solves."""
    problem, train_set, validation = small_heat
    network = heat_network(problem)
    max_gap = 1e-3
    control = truncation_gap(0.3, max_gap=max_gap, rtol_factor=0.1, rtol_min=1e-8)
    training = heat.train(problem, network, train_set, validation, unroll=2, optimizer=ADAM,
                          refinement=control, epochs=1, batch_size=6)
    (record,) = training.records
    first = record.rtol
    assert first < 0.3  # 0.3 is visible to the untrained network of a 25-dof rollout
    gap_first, its_conv, _ = heat_gap(network, problem, validation, first)
    gap_looser, _, _ = heat_gap(network, problem, validation, first * 10)
    assert gap_first <= max_gap < gap_looser
    tried = [0.3 * 0.1**k for k in range(round(np.log10(0.3 / first)) + 1)]
    calibration = its_conv + sum(heat_gap(network, problem, validation, r)[2] for r in tried)
    _, conv_1, rtol_1 = heat_gap(training.network, problem, validation, first)
    assert record.validation_iterations == calibration + conv_1 + rtol_1


def test_heat_training_feeds_the_gap_of_its_own_rollouts_and_counts_them(small_heat):
    """Each record's gap is the validation rollout error at the epoch's rtol against the
    converged one, recomputed here; the rollout at that rtol adds its iterations to the
    validation tally; a gap above max_gap tightens the next epoch's rtol."""
    problem, train_set, validation = small_heat
    control = truncation_gap(0.3, max_gap=1e-4, rtol_factor=0.1, rtol_min=1e-9, redo=False)
    training = heat.train(problem, heat_network(problem), train_set, validation, unroll=2,
                          optimizer=ADAM, refinement=control, epochs=4, batch_size=6)
    records = training.records
    last, previous = records[-1], records[-2]
    gap, its_conv, its_rtol = heat_gap(training.network, problem, validation, last.rtol)
    assert last.truncation_gap == pytest.approx(gap, rel=1e-8)
    assert last.validation_iterations - previous.validation_iterations == its_conv + its_rtol
    # the rule on the recorded gaps: tighten after an epoch whose gap exceeded max_gap
    for before, after in itertools.pairwise(records):
        expected = max(before.rtol * 0.1, 1e-9) if before.truncation_gap > 1e-4 else before.rtol
        assert after.rtol == pytest.approx(expected)
    assert all(r.truncation_gap <= 1e-4 or r.rtol > records[-1].rtol for r in records[:-1])


def test_a_training_without_the_gap_controller_records_no_gap(small_heat):
    """Converged solves, the tolerance mode a gap controller also trains in (the step
    program the trainings above compiled)."""
    problem, train_set, validation = small_heat
    training = heat.train(problem, heat_network(problem), train_set, validation, unroll=2,
                          optimizer=ADAM, refinement=pf.converged(1e-10), epochs=1,
                          batch_size=6)
    assert math.isnan(training.records[0].truncation_gap)


@pytest.fixture(scope="module")
def small_learned():
    """A 6x6 learned inverse, 16 training and 8 validation samples, an MLP [36, 8, 36]:
    (disc, problem, train_set, validation, network)."""
    disc = pf.discretize(pf.unit_square(6), dirichlet=0.0)
    problem = learned.learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)),
                                      supervised=1e-2)
    samples = learned.source_samples(problem, learned.random_sources(disc, 24, seed=0),
                                     noise=0.01, seed=1)
    train_set, validation = samples.take(np.arange(16)), samples.take(np.arange(16, 24))
    network = learned.mlp_init(jax.random.PRNGKey(0), [disc.n_dofs, 8, disc.n_dofs],
                               input_scale=float(np.std(np.asarray(samples.observations))),
                               output_scale=float(np.std(np.asarray(samples.sources))))
    # the scales as float64 arrays, as a trained network holds them: one validation program
    # for the untrained and the trained network
    return disc, problem, train_set, validation, jax.tree.map(np.asarray, network)


# the validation pass at a tolerance, compiled once for every rtol
validation_at = jax.jit(learned.validation)


def test_learned_training_feeds_the_gap_of_its_validation_misfit(small_learned):
    _, problem, train_set, validation, network = small_learned
    control = truncation_gap(0.3, max_gap=1e-4, rtol_min=1e-8, redo=False)
    training = learned.train(problem, network, train_set, validation, refinement=control,
                             optimizer=ADAM, epochs=2, batch_size=8)
    first, last = training.records
    misfit, _, its_conv = validation_at(training.network, problem, validation, rtol=1e-10)
    truncated, _, its_rtol = validation_at(training.network, problem, validation,
                                           rtol=last.rtol)
    assert last.validation_misfit == pytest.approx(float(misfit), rel=1e-10)
    assert last.truncation_gap == pytest.approx(abs(float(truncated) / float(misfit) - 1),
                                                rel=1e-8)
    assert last.validation_iterations - first.validation_iterations == \
        int(its_conv) + int(its_rtol)
    expected = max(first.rtol * 0.1, 1e-8) if first.truncation_gap > 1e-4 else first.rtol
    assert last.rtol == pytest.approx(expected)

    def untrained_gap(rtol):
        misfit = validation_at(network, problem, validation, rtol=1e-10)[0]
        return abs(float(validation_at(network, problem, validation, rtol=rtol)[0])
                   / float(misfit) - 1)

    assert first.rtol < 0.3 and untrained_gap(first.rtol) <= 1e-4 < untrained_gap(
        first.rtol * 10)


# --- redo: the epoch that tightened the solves is trained again --------------------------


def scheduled(rtols):
    """A tolerance-mode controller that trains epoch ``i`` at ``rtols[i]`` whatever it is fed."""
    base = truncation_gap(rtols[0], rtol_min=min(rtols), redo=False)

    def update(state, value, failed=False):
        epoch = int(state.count) + 1
        return state._replace(count=state.count + 1,
                              rtol=np.float64(rtols[min(epoch, len(rtols) - 1)]))

    return pf.Refinement(base.init, update, tolerance_mode=True)


def check_redo(train, records, max_gap):
    """A redo run (``records``) equals a run at its accepted levels, epoch by epoch, plus the
    work of the epochs it discarded: the same epoch from the same start at the level before."""
    rtols = [r.rtol for r in records]
    redone = [r.epoch - 1 for r in records if r.redone]
    assert redone and all(records[i].redone == 1 for i in redone)
    # a kept epoch's gap passed, or its level could not tighten further
    assert all(r.truncation_gap <= max_gap for r in records)
    replay = train(scheduled(rtols), len(records))
    assert [r.validation_error for r in replay.records] == [r.validation_error for r in records]
    discarded = 0
    for i in redone:
        tried = train(scheduled([*rtols[:i], rtols[i] * 10]), i + 1).records
        discarded += tried[i].primal_iterations - (tried[i - 1].primal_iterations if i else 0)
    assert discarded > 0
    assert records[-1].primal_iterations == replay.records[-1].primal_iterations + discarded
    return replay


def test_heat_training_redoes_the_epoch_that_tightened_its_solves(small_heat):
    """The untrained network passes rtol 3e-4; one epoch at lr 1e-2 later it does not (gap
    2.4e-4): epoch 1 is trained again at 3e-5 from where it started, and its first try's
    CG iterations stay counted."""
    problem, train_set, validation = small_heat

    def train(refinement, epochs):
        return heat.train(problem, heat_network(problem), train_set, validation, unroll=2,
                          optimizer=ADAM, refinement=refinement, epochs=epochs,
                          batch_size=6)

    training = train(truncation_gap(0.3, max_gap=1.2e-4, rtol_min=1e-9), 3)
    replay = check_redo(train, training.records, 1.2e-4)
    assert [r.redone for r in training.records] == [1, 0, 0]
    assert all(np.array_equal(a, b) for a, b in zip(
        jax.tree.leaves(training.network.params), jax.tree.leaves(replay.network.params),
        strict=True))


def test_learned_training_redoes_the_epoch_that_tightened_its_solves(small_learned):
    _, problem, train_set, validation, network = small_learned

    def train(refinement, epochs):
        return learned.train(problem, network, train_set, validation, refinement=refinement,
                             optimizer=ADAM, epochs=epochs, batch_size=8)

    training = train(truncation_gap(0.3, max_gap=1e-3, rtol_min=1e-8), 3)
    check_redo(train, training.records, 1e-3)
    assert training.records[-1].steps == 4 * 2  # the discarded try's steps ran too


def test_without_redo_the_epoch_that_tightened_is_kept(small_heat):
    problem, train_set, validation = small_heat
    training = heat.train(problem, heat_network(problem), train_set, validation, unroll=2,
                          optimizer=ADAM, epochs=2, batch_size=6,
                          refinement=truncation_gap(0.3, max_gap=1.2e-4, redo=False))
    first, second = training.records
    assert first.redone == second.redone == 0
    assert first.truncation_gap > 1.2e-4 and second.rtol == pytest.approx(first.rtol / 10)


# --- the scene kind ---------------------------------------------------------------------


def heat_table(**refinement):
    return {"name": "g", "mesh": {"generator": "unit_square", "n": 6},
            "heat": {"trajectories": 8, "validation_trajectories": 2, "test_trajectories": 2,
                     "epochs": 2},
            "refinement": {"kind": "gap", **refinement}}


def test_a_gap_scene_builds_the_controller_with_its_settings():
    scene = parse_scene(heat_table(max_gap=0.02, rtol=1e-3), source="g.toml")
    assert scene.refinement == GapSpec(max_gap=0.02, rtol=1e-3)
    control = controller(scene)
    state = control.update(control.init(), 0.03)
    assert control.monitor == "truncation_gap" and float(state.rtol) == pytest.approx(1e-4)
    assert control.redo and not controller(parse_scene(heat_table(redo=False),
                                                       source="g.toml")).redo
    assert control.reference_factor == 1e-2  # the API's default
    assert controller(parse_scene(heat_table(reference_factor=1e-10),
                                  source="g.toml")).reference_factor == 1e-10


@pytest.mark.parametrize("refinement, match", [
    (dict(max_gap=0), "max_gap"), (dict(rtol=1e-3, rtol_min=1e-2), "rtol_min"),
    (dict(K0=3), "K0"), (dict(redo="yes"), "redo"), (dict(reference_factor=0), "reference_factor"),
    (dict(reference_factor=1.0), "reference_factor")])
def test_bad_gap_tables_name_the_key(refinement, match):
    with pytest.raises(SceneError, match=match):  # K0 belongs to another kind
        parse_scene(heat_table(**refinement), source="g.toml")


def test_an_inverse_scene_refuses_the_gap_kind():
    table = {"name": "i", "mesh": {"generator": "unit_square", "n": 6},
             "inverse": {"unknown": "source", "truth": "1"}, "refinement": {"kind": "gap"}}
    with pytest.raises(SceneSolverConfigError, match=r"kind = 'gap'.*learned or heat"):
        parse_scene(table, source="i.toml")


# --- the example scene ------------------------------------------------------------------

GAP_SCENE = Path(__file__).resolve().parents[1] / "examples" / "scenes" / "heat_emulator_gap.toml"


@pytest.mark.parametrize("example, base, pairs", [
    (GAP_SCENE, "heat_emulator", {"correction nog gap": "correction nog converged",
                                  "correction wig gap": "correction wig converged"}),
    (GAP_SCENE.with_name("reaction_diffusion_gap.toml"), "reaction_diffusion",
     {"wig gap": "wig converged"}),
    (GAP_SCENE.with_name("heat_emulator_mixed_gap.toml"),
     GAP_SCENE.with_name("heat_emulator_mixed.toml"),
     {"mixed gap": "mixed converged"})])
def test_the_gap_examples_are_their_scenes_with_gap_runs_beside_converged_partners(
        example, base, pairs):
    gap, base = load_scene(example), load_scene(base)
    assert (gap.mesh, gap.pde, gap.heat, gap.optimizer, gap.study.band) == (
        base.mesh, base.pde, base.heat, base.optimizer, base.study.band)
    runs = dict(gap.runs())
    assert set(runs) == set(pairs) | set(pairs.values())
    for name, partner in pairs.items():
        assert runs[name].refinement == GapSpec()  # the API's defaults, redo included
        assert runs[partner].refinement.kind == "converged"
        assert runs[partner].heat == runs[name].heat


@pytest.mark.slow  # the trainer tests above record the gaps; heat studies' tests pair the runs
def test_a_shrunk_gap_study_pairs_the_gap_run_and_records_its_gaps(tmp_path):
    scene = with_overrides(load_scene(GAP_SCENE), {
        "mesh": {"n": 6}, "heat": {"trajectories": 8, "validation_trajectories": 2,
                                   "test_trajectories": 2, "hidden": [16], "epochs": 3,
                                   "batch_size": 12},
        "study": {"runs": [
            {"name": "correction nog gap", "heat": {"setup": "correction", "mode": "nog"}},
            {"name": "correction nog converged", "heat": {"setup": "correction", "mode": "nog"},
             "refinement": {"kind": "converged", "rtol": 1e-10}}]}})
    result = run_study(scene, tmp_path)
    rows = {row["run"]: row for row in result.summary}
    assert rows["correction nog gap"]["converged_run"] == "correction nog converged"
    records = [r for r in ResultsLog(tmp_path / "results.jsonl").records()
               if r["type"] == "epoch" and r["run"] == "correction nog gap"]
    assert len(records) == 3 and all(0 <= r["truncation_gap"] < math.inf for r in records)
