"""Batched inversion: one vmapped program equals looping invert over the members."""

import dataclasses

import numpy as np
import optax
import pytest

import prdp_fem as pf
from prdp_fem.bench.batch import noise_batch
from prdp_fem.cli.main import main
from prdp_fem.errors import ShapeError, SolverConfigError
from prdp_fem.inverse import (
    Validation,
    converged,
    fixed,
    invert,
    invert_batch,
    prdp,
)


def _relative(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.fixture(scope="module")
def noisy():
    """Four log-kappa problems on one mesh: inclusions of other places and contrasts, 1 %
    noise each, so that the members' PRDP controllers stall, and refine, at other steps."""
    disc = pf.discretize(pf.unit_square(8, "triangle"), element="P1", kappa_space="P1",
                         dirichlet=0.0)
    source = np.ones(disc.n_dofs)

    def member(seed, centre, contrast):
        m_true = disc.interpolate_kappa(lambda x: np.log(
            1 + contrast * ((x[0] - centre) ** 2 + (x[1] - 0.5) ** 2 < 0.06)))
        kappa = np.exp(m_true)
        state = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa),
                                            disc.rhs(kappa, source)).x)
        observation = pf.with_noise(pf.full_field(disc, u_true=state), 0.01, seed=seed)
        return pf.inverse_problem(disc, observation, unknown="log_kappa", alpha=1e-5,
                                  known=source, truth=m_true)

    return [member(seed, centre, contrast) for seed, (centre, contrast) in
            enumerate([(0.3, 1.0), (0.5, 4.0), (0.7, 9.0), (0.5, 0.5)])]


#: refines after two stalled steps: the members above refine at steps 7 to never in 15
EAGER = prdp(K0=1, dK=1, ema_window=2, delta=2)


# map: a second mode of the batch = loop check the vmap case makes in the default suite
# (test_bench_batch_prints_the_equality runs both with the slow cases)
@pytest.mark.parametrize("mode", ["vmap", pytest.param("map", marks=pytest.mark.slow)])
def test_a_batch_with_its_own_k_per_member_equals_looping_invert(noisy, mode):
    refinement = EAGER
    batch = invert_batch(noisy, refinement=refinement, steps=15, mode=mode)
    singles = [invert(problem, refinement=refinement, steps=15) for problem in noisy]
    schedules = [[record.iterations for record in h] for h in batch.histories]
    assert schedules == [[record.iterations for record in s.history] for s in singles]
    assert len({tuple(schedule) for schedule in schedules}) > 1  # the members' K differ
    for i, single in enumerate(singles):
        assert _relative(batch.params[i], single.params) <= 1e-12
        assert _relative(batch.fields[i], single.field) <= 1e-12
        np.testing.assert_allclose(batch.histories[i].column("loss"),
                                   single.history.column("loss"), rtol=1e-12)
        member = batch.member(i)
        assert member.history is batch.histories[i]
        assert int(member.refinement.iterations) == int(single.refinement.iterations)
    # everything that ran, every member: the loop's totals
    assert batch.primal_iterations == sum(s.history[-1].primal_iterations for s in singles)
    assert batch.adjoint_iterations == sum(s.history[-1].adjoint_iterations_total
                                           for s in singles)
    assert batch.size == 4 and batch.time > 0


@pytest.mark.slow  # two more programs to compile (10 s)
def test_unrolled_and_converged_batches_equal_their_loops(noisy):
    for refinement, gradient in ((fixed(6), "unrolled"), (converged(1e-10), "implicit")):
        batch = invert_batch(noisy[:3], refinement=refinement, gradient=gradient, steps=4)
        for i, problem in enumerate(noisy[:3]):
            single = invert(problem, refinement=refinement, gradient=gradient, steps=4)
            assert _relative(batch.params[i], single.params) <= 1e-12


@pytest.mark.slow  # one more program to compile (5 s)
def test_a_batch_of_sensor_sets_equals_its_loop():
    """Members observing at other points (as many of them): stacked observation operators."""
    disc = pf.discretize(pf.unit_square(8, "triangle"), element="P1", kappa_space="P0",
                         dirichlet=0.0)
    problems = [pf.inverse_problem(
        disc, pf.point_sensors(disc, points, data=np.ones(2)), unknown="source", alpha=1e-6)
        for points in ([[0.31, 0.47], [0.62, 0.23]], [[0.5, 0.5], [0.625, 0.25]])]
    batch = invert_batch(problems, refinement=fixed(5), steps=3)
    for i, problem in enumerate(problems):
        single = invert(problem, refinement=fixed(5), steps=3)
        assert _relative(batch.params[i], single.params) <= 1e-12


def test_a_batch_of_coefficients_stacks_the_systems():
    """Members with other known kappa: their frozen systems differ and are stacked."""
    base = noise_batch(8, 1)[0]
    disc = pf.discretize(pf.unit_square(8, "triangle"), element="P1", kappa_space="P0",
                         dirichlet=0.0)
    problems = [pf.inverse_problem(disc, base.observation, unknown="source", alpha=1e-6,
                                   regularization="l2", truth=np.asarray(base.truth),
                                   known=disc.interpolate_kappa(lambda x, c=c: 1 + c * x[0]))
                for c in (0.0, 1.0, 5.0)]
    # a small step program (L-BFGS's batched search: the noisy members' test above): the test
    # is about the stacked systems; five steps take the parameter error from 1 to 0.1-0.5
    sgd = optax.sgd(1e4)
    batch = invert_batch(problems, optimizer=sgd, refinement=fixed(8), steps=5)
    for i, problem in enumerate(problems):
        single = invert(problem, optimizer=sgd, refinement=fixed(8), steps=5)
        assert _relative(batch.params[i], single.params) <= 1e-12
    assert _relative(batch.params[0], batch.params[2]) > 1e-3  # other kappa, other answers


def test_a_shared_k_is_driven_by_the_batch_s_total_loss(noisy):
    refinement = EAGER
    batch = invert_batch(noisy, refinement=refinement, steps=30, shared_refinement=True)
    schedules = {tuple(record.iterations for record in h) for h in batch.histories}
    assert len(schedules) == 1 and len(batch.refinements) == 1
    # replay: one controller fed the sum of the members' losses picks the same K
    control, replayed = refinement.init(), []
    totals = np.sum([h.column("loss") for h in batch.histories], axis=0)
    for total in totals:
        replayed.append(control.settings()[0])
        control = refinement.update(control, float(total), False)
    assert tuple(replayed) == schedules.pop()
    assert int(batch.member(3).refinement.iterations) == int(control.iterations)
    assert len(set(replayed)) > 1  # it refined


def test_init_per_member_or_shared(noisy):
    n = noisy[0].n_parameters
    starts = np.outer(np.arange(1.0, 4.0), np.ones(n))
    batch = invert_batch(noisy[:3], refinement=fixed(4), steps=0, init=starts)
    np.testing.assert_array_equal(np.asarray(batch.params), starts)
    shared = invert_batch(noisy[:3], refinement=fixed(4), steps=0, init=np.full(n, 2.0))
    np.testing.assert_array_equal(np.asarray(shared.params), 2.0)
    with pytest.raises(ShapeError, match=r"init: shape \(2, \d+\); expected"):
        invert_batch(noisy[:3], steps=1, init=starts[:2])


def test_bad_batches_are_refused_naming_the_member(noisy):
    with pytest.raises(ShapeError, match=r"problems\[1\]: a problem of another structure"):
        invert_batch([noise_batch(8, 1)[0], noise_batch(6, 1)[0]], steps=1)  # other meshes
    disc = pf.discretize(pf.unit_square(8, "triangle"), element="P1", kappa_space="P0",
                         dirichlet=0.0)
    sensors = [pf.point_sensors(disc, np.random.default_rng(s).uniform(0.1, 0.9, (m, 2)),
                                data=np.zeros(m)) for s, m in ((0, 5), (1, 7))]
    problems = [pf.inverse_problem(disc, o, unknown="source", alpha=1e-6) for o in sensors]
    with pytest.raises(ShapeError, match=r"problems\[1\]: a problem of another structure"):
        invert_batch(problems, steps=1)  # 5 and 7 sensors
    longer = dataclasses.replace(problems[0], truth=np.zeros(problems[0].n_parameters + 1))
    with pytest.raises(ShapeError, match=r"problems\[1\]\.truth: shape \(\d+,\), dtype "
                                         r"float64; expected \(\d+,\), float64 as in"):
        invert_batch([dataclasses.replace(problems[0], truth=np.zeros(81)), longer], steps=1)
    with pytest.raises(SolverConfigError, match="an empty batch"):
        invert_batch([], steps=1)
    with pytest.raises(SolverConfigError, match="expected a sequence of InverseProblem"):
        invert_batch(noisy[0], steps=1)
    with pytest.raises(SolverConfigError, match="RebuiltAMG"):
        invert_batch(noisy, steps=1, preconditioner=pf.linalg.RebuiltAMG())
    with pytest.raises(SolverConfigError, match="monitor="):
        invert_batch(noisy, steps=1, monitor=Validation(every=1))
    with pytest.raises(SolverConfigError, match=r"mode='pmap': expected one of \['vmap', 'map'\]"):
        invert_batch(noisy, steps=1, mode="pmap")


@pytest.mark.slow  # three programs to compile (12 s)
def test_bench_batch_prints_the_equality(capsys):
    assert main(["bench", "batch", "--sizes", "1", "3", "--n", "4", "--steps", "2",
                 "--repeats", "1"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[2:6]]
    assert [(int(row[0]), row[1]) for row in rows] == [(1, "vmap"), (1, "map"), (3, "vmap"),
                                                       (3, "map")]
    assert all(float(row[-1]) <= 1e-12 for row in rows)  # max diff: batch = loop


def test_bench_batch_refuses_bad_sizes(capsys):
    assert main(["bench", "batch", "--sizes", "0"]) == 2
    assert "--sizes 0: expected integers >= 1" in capsys.readouterr().err
