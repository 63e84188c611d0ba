"""The reference's regime, reproduced: ``examples/reference_1d.py`` against an independent NumPy
transcription of the PRDP reference code's one-parameter Poisson notebook (tum-pbs/PRDP), and
its numbers pinned.

The transcription keeps the notebook's names and operations: the dense Laplacian
``A_matrix``, ``forward_solve_jacobi`` (``u = (b - (U + L) u) / D``), the custom JVP of
``u_solve`` (the tangent is the same Jacobi solve of ``b_dot``), ``squareloss_fn``,
``update_fn`` (one gradient-descent step at ``n_inner``) and the notebook's own
``should_refine`` (raw error ratio over ``error_window = 2``, checkpoint from 100); only
``jacfwd`` is written out by hand (the derivative of the scalar loss in theta). float64, where
the notebook ran in JAX's default float32.
"""

import numpy as np
import pytest

from prdp_fem.errors import SolverConfigError
from prdp_fem.inverse import prdp, state_to_dict

# ------------------------------------------------------------------------------------------
# the reference notebook, in NumPy
# ------------------------------------------------------------------------------------------

THETA_REF = 2.0
N_DOF = 30
THETA_INIT = 5.0
N_OUTER = 180
LR = 275
N_INNER_MAX = 600
N_INNER_INIT, N_INNER_STEP = 25, 10
TAU_STEP = 0.92
ERROR_WINDOW = 2


def A_matrix(n_dof):
    A_super_diag = np.diag(np.ones(n_dof - 1), k=1)
    A_diag = np.diag(-2 * np.ones(n_dof))
    A_sub_diag = np.diag(np.ones(n_dof - 1), k=-1)
    h = 1 / (n_dof + 1)
    factor = 1 / (h * h)
    return factor * (A_super_diag + A_diag + A_sub_diag)


def rhs_sine_fn(theta, x):
    return -theta * np.sin(2 * np.pi * x)


def forward_solve_jacobi(A, b, n_iterations, u_initial):
    U = np.triu(A, k=1)
    L = np.tril(A, k=-1)
    D = np.diag(A).astype(float)
    u, iterates = u_initial, [u_initial]
    for _ in range(n_iterations):
        u = (b - np.dot(U + L, u)) / D
        iterates.append(u)
    return np.asarray(iterates)


def squareloss_fn(solution_history, ground_truth):
    N = ground_truth.shape[0]
    return np.linalg.norm(solution_history - ground_truth, axis=-1) ** 2 / (2 * N)


def reference_run():
    """The notebook's PRDP cell: K schedule (``n_inner_hist_prdp``), theta and its error."""
    x = np.linspace(0, 1, N_DOF + 2)[1:-1]
    A = A_matrix(N_DOF)
    u_ref = np.linalg.solve(A, rhs_sine_fn(THETA_REF, x))
    U_INIT = np.zeros(N_DOF)

    def u_solve(b, n_inner, u_init):
        return forward_solve_jacobi(A, b, n_inner, u_init)

    def u_solve_jvp(b_dot, n_inner, u_init):  # the notebook's custom JVP: Jacobi on b_dot
        return forward_solve_jacobi(A, b_dot, n_inner, u_init)

    def loss_fn_prdp(theta, n_inner):
        u = u_solve(rhs_sine_fn(theta, x), n_inner, U_INIT)[-1]
        return squareloss_fn(u, u_ref)

    def grad_loss_fn_prdp(theta, n_inner):  # jacfwd(loss_fn_prdp), by the chain rule
        u = u_solve(rhs_sine_fn(theta, x), n_inner, U_INIT)[-1]
        u_dot = u_solve_jvp(-np.sin(2 * np.pi * x), n_inner, U_INIT)[-1]
        return np.dot(u - u_ref, u_dot) / u_ref.shape[0]

    def update_fn(theta, n_inner, lr):
        theta_new = theta - lr * grad_loss_fn_prdp(theta, n_inner)
        loss = loss_fn_prdp(theta_new, n_inner)
        return loss, theta_new

    def theta_error_fn(theta):
        return np.abs(theta - THETA_REF) / np.abs(THETA_REF)

    theta = THETA_INIT
    n_inner = N_INNER_INIT
    theta_hist = [theta]
    theta_error_hist_prdp = [theta_error_fn(theta)]
    n_inner_hist_prdp = [N_INNER_INIT]
    should_refine.error_checkpoint = 100
    for _ in range(N_OUTER):
        _, theta = update_fn(theta, int(n_inner), LR)
        theta_hist.append(theta)
        theta_error_hist_prdp.append(theta_error_fn(theta))
        n_inner_hist_prdp.append(int(n_inner))
        if should_refine(np.array(theta_error_hist_prdp), stepping_threshold=TAU_STEP,
                         error_window=ERROR_WINDOW):
            n_inner = min(n_inner + N_INNER_STEP, N_INNER_MAX)
    return n_inner_hist_prdp, np.asarray(theta_hist), np.asarray(theta_error_hist_prdp)


def should_refine(error_hist, stepping_threshold=0.98, nmax_threshold=0.9, error_window=3):
    """The notebook's rule (its own cell, not the EMA version of its ``src/prdp.py``)."""
    assert error_window > 1, "error_window should be greater than 1"
    if len(error_hist) <= error_window:
        return False
    error_hist = np.array(error_hist)
    error_ratio = error_hist[-1] / error_hist[-error_window]
    if error_ratio > stepping_threshold:  # implies plateauing of error history
        checkpoint_ratio = error_hist[-1] / should_refine.error_checkpoint
        if checkpoint_ratio < nmax_threshold or checkpoint_ratio > 1:
            should_refine.error_checkpoint = error_hist[-1]
            return True
        return False  # no improvement against checkpoint => reached Nmax
    return False  # error history hasn't plateaued => continue using current N


def notebook_schedule(errors, K0=25, dK=10, K_max=600):
    """K after each value of ``errors`` (the first one the initial error) by the notebook."""
    should_refine.error_checkpoint = 100
    K, ks = K0, []
    for t in range(1, len(errors) + 1):
        if should_refine(np.array(errors[:t]), stepping_threshold=TAU_STEP,
                         error_window=ERROR_WINDOW):
            K = min(K + dK, K_max)
        ks.append(K)
    return ks


def package_schedule(controller, errors):
    state, ks = controller.init(), []
    for e in errors:
        state = controller.update(state, e)
        ks.append(int(state.iterations))
    return ks


REFERENCE = reference_run()

# ------------------------------------------------------------------------------------------
# the rule
# ------------------------------------------------------------------------------------------

SEQUENCES = {
    "plateau, then a lower one": [1.0] * 5 + [0.5] * 10 + [0.49] * 10,
    "slow fall": list(0.95 ** np.arange(40)),
    "stalls and rises": [1.0, 0.9, 0.89, 0.95, 0.96, 0.5, 0.49, 0.49, 0.6, 0.61, 0.3, 0.2],
    "fast fall": list(0.5 ** np.arange(30)),
}


@pytest.fixture(scope="module")
def module(load_example):
    return load_example("reference_1d")


@pytest.fixture(scope="module")
def example(module):
    return module.main()


@pytest.mark.parametrize("name", SEQUENCES)
def test_the_notebook_rule_is_the_package_controller(module, name):
    errors = SEQUENCES[name]
    assert package_schedule(module.reference_controller(), errors) == notebook_schedule(errors)
    # on the reference run's own errors too
    errors = list(REFERENCE[2])
    assert package_schedule(module.reference_controller(), errors) == notebook_schedule(errors)


def test_initial_checkpoint_option():
    state = prdp(initial_checkpoint=100.0).init()
    assert state_to_dict(state)["checkpoint"] == 100.0
    assert state_to_dict(prdp().init())["checkpoint"] is None  # the first value, once seen
    for bad in (0.0, -1.0, float("nan"), float("inf"), True, "100"):
        with pytest.raises(SolverConfigError, match="initial_checkpoint"):
            prdp(initial_checkpoint=bad)
    # stall_on_failure: the first step's failure stays exempt with a given checkpoint
    controller = prdp(K0=10, dK=10, stall_on_failure=True, initial_checkpoint=100.0)
    state = controller.update(controller.init(), 1.0, failed=True)
    assert int(state.iterations) == 10
    state = controller.update(state, 0.99, failed=True)  # a later one refines (K still K0)
    assert int(state.iterations) == 20


def test_the_checkpoint_matters_on_this_run(module, example):
    """With the package's default checkpoint (the first error, 1.5), the first stall (the error
    creeps down by 0.02 % a step at K = 25) is judged 'enough' and K never moves: the notebook's
    checkpoint of 100 is needed."""
    default = prdp(K0=25, dK=10, K_max=600, tau_step=TAU_STEP, ema_window=1, delta=2)
    r = module.run(module.build(), "jacobi, implicit", refinement=default, steps=60)
    assert set(r.schedule) == {25} and r.error[-1] == pytest.approx(1.48625, abs=1e-5)


# ------------------------------------------------------------------------------------------
# the example against the notebook, and its numbers
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["jacobi, unrolled", "jacobi, implicit"])
def test_jacobi_runs_reproduce_the_notebook(example, name):
    schedule, theta, errors = REFERENCE
    r = example["runs"][name]
    assert r.schedule == schedule
    np.testing.assert_allclose(r.theta, theta, rtol=0, atol=1e-10)
    np.testing.assert_allclose(r.error, errors, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("name", ["jacobi, unrolled", "jacobi, implicit"])
def test_jacobi_schedule_saving_and_error_are_pinned(example, name):
    r = example["runs"][name]
    assert len(r.schedule) == 181 and r.schedule[:5] == [25, 25, 25, 35, 35]
    assert r.refinements == 67 and r.schedule.index(600) == 161 and r.schedule[-1] == 600
    assert sum(r.schedule[:170]) == 50465
    assert r.saving == pytest.approx(1 - 50465 / 75000, abs=1e-15)  # 32.71 %
    assert r.error[-1] == pytest.approx(8.1308e-6, rel=1e-4)


def test_fixed_k600_run(example):
    """The notebook's 'fully converged' baseline: K = 600 on every step."""
    r = example["runs"]["jacobi, K = 600"]
    assert set(r.schedule) == {600}
    assert r.error[-1] == pytest.approx(4.1244e-6, rel=1e-4)
    assert example["converged_reaches_prdp_error_at"] == 134


@pytest.mark.parametrize("name", ["pcg, unrolled", "pcg, implicit"])
def test_pcg_has_nothing_to_refine(example, name):
    r = example["runs"][name]
    assert set(r.schedule) == {25} and r.refinements == 0
    assert example["pcg_converged_after"] == 1
    # the error of converged solves, to the digits the solves carry
    assert r.error[-1] == pytest.approx(example["converged_final_error"], rel=1e-6)
    assert example["converged_final_error"] == pytest.approx(4.4624e-8, rel=1e-4)
