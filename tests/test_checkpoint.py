"""Saved, resumable training: a run interrupted and resumed from its checkpoints ends
bit for bit where an uninterrupted run ends (Adam and L-BFGS, the learned inverse and the heat
stepper), and checkpoints of another training are refused."""

import math

import jax
import numpy as np
import optax
import pytest

import prdp_fem as pf
from prdp_fem.errors import CheckpointError, ShapeError
from prdp_fem.inverse import prdp
from prdp_fem.learning import Checkpoints, heat, learned, load_params, read_metadata

# one object: the trainings of equal settings below share one compiled step
ADAM = optax.adam(3e-3)

# refines at every other epoch: the controller's state is part of what resumes
EAGER_PRDP = prdp(K0=2, dK=2, tau_step=0.01, ema_window=1, delta=2, initial_checkpoint=100.0)


class Stop(Exception):
    """Raised by a callback: the process 'dies' after an epoch."""


def stop_after(epoch: int, seen: list):
    def callback(record):
        seen.append(record)
        if record.epoch == epoch:
            raise Stop

    return callback


@pytest.fixture(scope="module")
def inverse():
    disc = pf.discretize(pf.unit_square(5), dirichlet=0.0)
    problem = learned.learned_inverse(disc, pf.full_field(disc, data=np.zeros(disc.n_dofs)),
                                      supervised=1e-2)
    sources = learned.random_sources(disc, 20, seed=0, width=0.2)
    samples = learned.source_samples(problem, sources, noise=0.01, seed=1)
    network = learned.mlp_init(jax.random.PRNGKey(0), [disc.n_dofs, 16, disc.n_dofs],
                               input_scale=float(np.std(np.asarray(samples.observations))),
                               output_scale=float(np.std(sources)))
    return (problem.with_residual(), network, samples.take(np.arange(12)),
            samples.take(np.arange(12, 16)), samples.take(np.arange(16, 20)))


def untimed(records):
    """The records without their wall-clock time, NaN fields (no test set, no truncation gap
    measured) as None so that equal records compare equal."""
    return [type(r)(*(None if isinstance(v, float) and math.isnan(v) else v
                      for v in r._replace(time=0.0))) for r in records]


def leaves_equal(a, b) -> bool:
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
               zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


@pytest.mark.parametrize("optimizer, batch_size", [(ADAM, 4), (optax.lbfgs(), 12)],
                         ids=["adam", "lbfgs"])
def test_resumed_learned_training_equals_an_uninterrupted_one(inverse, tmp_path, optimizer,
                                                              batch_size):
    problem, network, train_set, validation_set, test_set = inverse
    options = dict(optimizer=optimizer, refinement=EAGER_PRDP, epochs=7, batch_size=batch_size,
                   test_set=test_set)
    whole = learned.train(problem, network, train_set, validation_set, **options)
    directory = tmp_path / "run"
    seen = []
    with pytest.raises(Stop):  # dies after epoch 5: its last checkpoint is epoch 4
        learned.train(problem, network, train_set, validation_set,
                      checkpoints=Checkpoints(directory, every=2), callback=stop_after(5, seen),
                      **options)
    assert read_metadata(directory)["epochs"] == [2, 4]
    replayed = []
    resumed = learned.train(problem, network, train_set, validation_set,
                            checkpoints=Checkpoints(directory, every=2, resume=True),
                            callback=replayed.append, **options)
    assert untimed(resumed.records) == untimed(whole.records)
    assert untimed(replayed) == untimed(whole.records)  # the restored records replayed first
    assert leaves_equal(resumed.network.params, whole.network.params)
    assert leaves_equal(resumed.refinement, whole.refinement)
    assert len({r.iterations for r in whole.records}) > 1  # PRDP refined: its state mattered
    assert np.isfinite(whole.records[-1].test_error)
    assert read_metadata(directory)["epochs"] == [6, 7]  # keep 2, the last one forced
    params, epoch = load_params(directory, network.params, kind="learned", metadata={})
    assert epoch == 7 and leaves_equal(params, whole.network.params)


@pytest.fixture(scope="module")
def heat_case():
    """A 4x4 heat problem, 8 training, 2 validation and 2 test trajectories of 4 steps and
    an untrained network: (problem, train_set, validation_set, test_set, network)."""
    disc = pf.discretize(pf.unit_square(4), dirichlet=0.0)
    problem = heat.heat_problem(disc, 0.02)
    data = heat.reference_trajectories(disc, heat.random_initial_states(disc, 12, seed=0),
                                       dt=0.02, steps=4, substeps=2)
    train_set = data.take(np.arange(8))
    # the scales as float64 arrays, as a trained network holds them: a gap-fed training
    # validates the untrained network before its first step, and Python-float scales would
    # compile its validation passes a second time for the trained one
    network = jax.tree.map(np.asarray, heat.initial_network(problem, train_set, "correction",
                                                            (16,)))
    return (problem, train_set, data.take(np.arange(8, 10)), data.take(np.arange(10, 12)),
            network)


def heat_whole_and_resumed(heat_case, tmp_path, **options):
    """A small heat training run whole, and stopped after epoch 4 of 5 (checkpoints every 3)
    then resumed: both runs' trainings."""
    problem, train_set, validation_set, test_set, network = heat_case
    options = dict(setup="correction", unroll=2, epochs=5, batch_size=8,
                   optimizer=optax.adam(1e-3), test_set=test_set, **options)
    whole = heat.train(problem, network, train_set, validation_set, **options)
    with pytest.raises(Stop):
        heat.train(problem, network, train_set, validation_set, callback=stop_after(4, []),
                   checkpoints=Checkpoints(tmp_path, every=3), **options)
    resumed = heat.train(problem, network, train_set, validation_set,
                         checkpoints=Checkpoints(tmp_path, every=3, resume=True), **options)
    assert untimed(resumed.records) == untimed(whole.records)
    assert leaves_equal(resumed.network.params, whole.network.params)
    return whole, resumed


def test_heat_training_resumes_bit_for_bit(heat_case, tmp_path):
    whole, resumed = heat_whole_and_resumed(heat_case, tmp_path, mode="wig",
                                            refinement=EAGER_PRDP)
    assert len({r.iterations for r in whole.records}) > 1
    assert resumed.records[-1].adjoint_iterations_total == \
        whole.records[-1].adjoint_iterations_total > 0


def test_a_gap_refined_heat_training_resumes_bit_for_bit(heat_case, tmp_path):
    """The first level is settled once, before epoch 1; a resumed run's tolerances, gaps and
    validation tally are the uninterrupted run's."""
    whole, _ = heat_whole_and_resumed(
        heat_case, tmp_path, mode="nog",
        refinement=pf.truncation_gap(0.3, max_gap=1e-4, rtol_min=1e-9))
    assert whole.records[0].rtol < 0.3  # settled before epoch 1
    assert all(0 <= r.truncation_gap <= 1e-4 for r in whole.records)


def test_checkpoints_of_another_training_are_refused(inverse, tmp_path):
    problem, network, train_set, validation_set, _ = inverse
    options = dict(optimizer=ADAM, epochs=2, batch_size=4)
    learned.train(problem, network, train_set, validation_set,
                  checkpoints=Checkpoints(tmp_path, every=1, metadata={"scene": "a"}), **options)
    with pytest.raises(CheckpointError, match="holds checkpoints already"):
        learned.train(problem, network, train_set, validation_set,
                      checkpoints=Checkpoints(tmp_path, metadata={"scene": "a"}), **options)
    with pytest.raises(CheckpointError, match="another metadata"):
        learned.train(problem, network, train_set, validation_set,
                      checkpoints=Checkpoints(tmp_path, resume=True, metadata={"scene": "b"}),
                      **options)
    with pytest.raises(CheckpointError, match="another training"):
        load_params(tmp_path, network.params, kind="heat", metadata={"scene": "a"})
    with pytest.raises(CheckpointError, match="holds params of 4 arrays"):  # other shapes
        wider = learned.mlp_init(jax.random.PRNGKey(0), [problem.system.n_dofs, 17,
                                                         problem.system.n_dofs])
        load_params(tmp_path, wider.params, kind="learned", metadata={"scene": "a"})
    with pytest.raises(CheckpointError, match="holds state of"):  # another optimiser
        learned.train(problem, network, train_set, validation_set,
                      checkpoints=Checkpoints(tmp_path, resume=True, metadata={"scene": "a"}),
                      **{**options, "optimizer": optax.sgd(1e-3)})
    with pytest.raises(CheckpointError, match="expected at most epochs=1"):
        learned.train(problem, network, train_set, validation_set,
                      checkpoints=Checkpoints(tmp_path, resume=True, metadata={"scene": "a"}),
                      **{**options, "epochs": 1})
    with pytest.raises(CheckpointError, match="no finished checkpoint"):
        read_metadata(tmp_path / "empty")
    with pytest.raises(CheckpointError, match="every=0"):
        Checkpoints(tmp_path, every=0)
    with pytest.raises(CheckpointError, match="not plain JSON"):
        Checkpoints(tmp_path, metadata={"split": np.arange(3)})


def test_an_empty_split_is_refused(inverse):
    problem, network, train_set, validation_set, _ = inverse
    with pytest.raises(ShapeError, match="test_set: no samples"):
        learned.train(problem, network, train_set, validation_set, epochs=1, batch_size=4,
                      test_set=validation_set.take(np.arange(0)))


class DiesAfter:
    """A study's progress whose ``step`` (after each epoch record) kills the run at the
    ``n``-th epoch."""

    def __init__(self, n: int):
        self.n, self.epochs = n, 0

    def run_started(self, name, steps):
        pass

    def step(self):
        self.epochs += 1
        if self.epochs == self.n:
            raise Stop

    def run_finished(self, name, skipped):
        pass

    def stop_if_requested(self):
        pass


STUDY = """
name = "resumable"
[mesh]
n = 5
[inverse]
unknown = "source"
[learned]
samples = 8
validation_samples = 4
test_samples = 4
hidden = [4]
epochs = 5
batch_size = 4
checkpoint_every = 2
[refinement]
kind = "prdp"
K0 = 2
dK = 2
tau_step = 0.01
ema_window = 1
delta = 2
[optimizer]
name = "adam"
learning_rate = 3e-3
[[study.runs]]
name = "prdp"
"""


def test_a_killed_study_resumes_its_run_from_the_last_checkpoint(tmp_path):
    import tomllib

    from prdp_fem.scene import parse_scene
    from prdp_fem.studies.runner import ResultsLog, checkpoint_directory, run_study

    scene = parse_scene(tomllib.loads(STUDY))
    whole = run_study(scene, tmp_path / "whole")
    out = tmp_path / "killed"
    with pytest.raises(Stop):  # the first run dies after epoch 3: its checkpoint is epoch 2
        run_study(scene, out, progress=DiesAfter(3))
    run = whole.summary[0]["run"]
    assert read_metadata(checkpoint_directory(out, run))["epochs"] == [2]
    resumed = run_study(scene, out, resume=True)

    def epochs(directory, attempt):
        return [{k: v for k, v in r.items() if k not in ("time", "attempt")}
                for r in ResultsLog(directory / "results.jsonl").records()
                if r["type"] == "epoch" and r["run"] == run and r["attempt"] == attempt]

    assert epochs(out, 2) == epochs(tmp_path / "whole", 1)  # restored, then trained on
    assert len({r["iterations"] for r in epochs(out, 2)}) > 1
    assert resumed.summary[0]["final_error"] == whole.summary[0]["final_error"]
