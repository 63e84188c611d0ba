"""Discretisation: the assembly map against scikit-fem, boundary data, convergence rates."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import skfem
from conftest import MESH_DIR
from skfem.helpers import dot, grad

import prdp_fem as pf
from prdp_fem._sorting import unique_with_inverse


def skfem_reference(disc, kappa):
    """Full operator assembled directly by scikit-fem with the kappa field interpolated."""
    form = skfem.BilinearForm(lambda u, v, w: w.k * dot(grad(u), grad(v)))
    return form.assemble(disc.basis, k=disc.kappa_basis.interpolate(kappa)).tocsr()


CASES = [
    (lambda: pf.unit_square(5), "P1"), (lambda: pf.unit_square(3), "P2"),
    (lambda: pf.unit_cube(2), "P1"), (lambda: pf.unit_cube(2), "P2"),
    (lambda: pf.unit_square(4, "quad"), "Q1"), (lambda: pf.unit_cube(2, "hexahedron"), "Q1"),
]


@pytest.mark.parametrize("kappa_space", ["P0", "P1", "P2"])
@pytest.mark.parametrize(("make", "element"), CASES)
def test_assembly_map_equals_scikit_fem(make, element, kappa_space):
    def g(x):
        return 1.0 + x[0] ** 2 - x[1]

    disc = pf.discretize(make(), element=element, kappa_space=kappa_space, dirichlet=g)
    rng = np.random.default_rng(0)
    kappa = rng.uniform(0.5, 2.0, disc.n_kappa)
    full = skfem_reference(disc, kappa)
    free, fixed = disc.free_dofs, disc.dirichlet_dofs
    assert abs(disc.stiffness_matrix(kappa) - full[free][:, free]).max() < 1e-13
    lifted = -full[free][:, fixed] @ disc.dirichlet_values
    np.testing.assert_allclose(disc.rhs(kappa), lifted, atol=1e-13)
    # the JAX side gives the same operator and right-hand side (one compiled program, not
    # one per eager operation and shape)
    op, rhs = jax.jit(lambda k: (disc.system.operator(k), disc.system.rhs(k)))(kappa)
    assert abs(op.to_scipy() - disc.stiffness_matrix(kappa)).max() < 1e-13
    np.testing.assert_allclose(rhs, disc.rhs(kappa), atol=1e-13)


def _manufactured_variable_kappa():
    """u = sin(pi x) sin(pi y), kappa = 1 + x^2 y, f = -div(kappa grad u)."""
    def kappa(x):
        return 1.0 + x[0] ** 2 * x[1]

    def u(x):
        return np.sin(np.pi * x[0]) * np.sin(np.pi * x[1])

    def f(x):
        ux = np.pi * np.cos(np.pi * x[0]) * np.sin(np.pi * x[1])
        uy = np.pi * np.sin(np.pi * x[0]) * np.cos(np.pi * x[1])
        return kappa(x) * 2 * np.pi ** 2 * u(x) - (2 * x[0] * x[1] * ux + x[0] ** 2 * uy)
    return kappa, u, f


# quads with the slow cases: the same assembly path as triangles, another element
@pytest.mark.parametrize("cell", ["triangle", pytest.param("quad", marks=pytest.mark.slow)])
def test_a_variable_kappa_at_element_order_keeps_p2_s_rates(cell):
    """P2/Q2 with kappa = 1 + x^2 y: assembled at the quadrature points (a function) or
    interpolated into the state's order ("P2"), L2 rate 3 and H1 rate 2; interpolated into
    P1, the coefficient's O(h^2) error holds the L2 rate to 2."""
    kappa, u, f = _manufactured_variable_kappa()

    def grad_u(x):
        return np.pi * np.stack([np.cos(np.pi * x[0]) * np.sin(np.pi * x[1]),
                                 np.sin(np.pi * x[0]) * np.cos(np.pi * x[1])])

    def rates(kappa_space, as_function):
        l2, h1 = [], []
        for n in (4, 8, 16):
            disc = pf.discretize(pf.unit_square(n, cell), element="P2", kappa_space=kappa_space,
                                 dirichlet=0.0)
            A, b = disc.host_system_at(kappa if as_function else disc.interpolate_kappa(kappa))
            uh = disc.expand(pf.direct_solve(A, b + disc.load_vector(f)).x)
            l2.append(pf.fem.l2_error(disc, uh, u))
            h1.append(pf.fem.h1_error(disc, uh, grad_u))
        return np.log2(l2[-2] / l2[-1]), np.log2(h1[-2] / h1[-1])

    for kappa_space, as_function in (("P0", True), ("P2", False)):
        l2_rate, h1_rate = rates(kappa_space, as_function)
        assert l2_rate == pytest.approx(3.0, abs=0.1) and h1_rate == pytest.approx(2.0, abs=0.1)
    assert rates("P1", False)[0] == pytest.approx(2.0, abs=0.2)


def test_a_function_kappa_is_the_same_operator_as_its_values_where_they_agree():
    """A constant or a P1-exact coefficient gives the operator the vector gives; one that
    is not positive at a quadrature point, or not finite, is refused by name."""
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P1", dirichlet=0.0)
    def linear(x):
        return 2.0 + x[0] - 0.5 * x[1]

    for fn in (lambda x: 3.0, linear):
        A_fn, b_fn = disc.host_system_at(fn)
        A_vec, b_vec = disc.host_system_at(disc.interpolate_kappa(fn))
        assert abs(A_fn - A_vec).max() < 1e-13
        np.testing.assert_allclose(b_fn, b_vec, atol=1e-13)
    with pytest.raises(pf.CoefficientError, match=r"kappa\(x\) is <= 0 at \d+ quadrature"):
        disc.host_system_at(lambda x: x[0] - 0.5)
    with pytest.raises(pf.CoefficientError, match=r"NaN/Inf values at quadrature points"):
        disc.host_system_at(lambda x: np.where(x[0] > 0.5, np.inf, 1.0))
    tensor = pf.discretize(pf.unit_square(2), kappa_kind="tensor", dirichlet=0.0)
    with pytest.raises(pf.CoefficientError, match="a function for a tensor coefficient"):
        tensor.host_system_at(lambda x: 1.0)


@jax.jit
def _frozen_at(frozen, s, f):
    """The frozen system's operator, and its right-hand sides with the source ``f`` and
    without, at the scale ``s`` (one compiled program per system's structure)."""
    return frozen.operator(s), frozen.rhs(s, f), frozen.rhs(s)


def _frozen_gap(frozen, disc, kappa):
    """Largest entry gap of the frozen system (at scale 1) against the kappa map's, relative
    to the largest entry, for the operator and the right-hand side with a source."""
    f = np.cos(np.arange(disc.n_dofs))
    A, b, _ = _frozen_at(frozen, jnp.ones(1), jnp.asarray(f))
    A, reference = A.to_scipy(), disc.stiffness_matrix(kappa)
    b_ref = disc.rhs(kappa, f)
    return (abs(A - reference).max() / abs(reference).max(),
            np.abs(b - b_ref).max() / np.abs(b_ref).max())


@pytest.mark.parametrize("kappa_space", ["P0", "P1"])
@pytest.mark.parametrize(("make", "element"), CASES)
def test_system_at_kappa_equals_the_kappa_map_there(make, element, kappa_space):
    """The frozen system (assembled at kappa in one pass) has the kappa map's operator and
    right-hand side at kappa, Dirichlet data and the source included, and scales with s."""
    def g(x):
        return 1.0 + x[0] ** 2 - x[1]

    disc = pf.discretize(make(), element=element, kappa_space=kappa_space, dirichlet=g)
    kappa = np.random.default_rng(1).uniform(0.5, 2.0, disc.n_kappa)
    frozen = disc.system_at(kappa)
    assert frozen.n_kappa == 1 and frozen.n_free == disc.n_free
    assert max(_frozen_gap(frozen, disc, kappa)) < 1e-14
    f = np.sin(np.arange(disc.n_dofs))
    A, b = disc.host_system_at(kappa, f)  # the same on the host, as SciPy and NumPy
    reference = disc.stiffness_matrix(kappa)
    assert abs(A - reference).max() < 1e-14 * abs(reference).max()
    np.testing.assert_allclose(b, disc.rhs(kappa, f), rtol=0,
                               atol=1e-14 * np.abs(disc.rhs(kappa, f)).max())
    # linear in the scale: A(s) = s A(kappa), and b's lifting term scales with it
    A_s, _, b_s = _frozen_at(frozen, jnp.asarray([3.0]), jnp.asarray(f))
    scaled = A_s.to_scipy() - 3.0 * disc.stiffness_matrix(kappa)
    assert abs(scaled).max() < 1e-13 * abs(disc.stiffness_matrix(kappa)).max()
    np.testing.assert_allclose(b_s, disc.rhs(3.0 * kappa), rtol=1e-13,
                               atol=1e-13 * np.abs(disc.rhs(kappa)).max())


@pytest.mark.parametrize(("make", "element"), [
    (lambda: pf.unit_square(4), "P2"), (lambda: pf.unit_square(3, "quad"), "Q2"),
    (lambda: pf.unit_cube(2), "P1"), (lambda: pf.unit_cube(1, "hexahedron"), "Q2")])
def test_system_at_a_tensor_kappa_and_neumann_data(make, element):
    mesh = make()
    dim = mesh.dim()
    disc = pf.discretize(mesh, element=element, kappa_space="P1", kappa_kind="tensor",
                         dirichlet={"left": 1.0}, neumann={"right": lambda x: x[1]})

    def tensor(x):  # symmetric positive definite, varying in space
        k = np.zeros((dim, dim, x.shape[1]))
        for i in range(dim):
            k[i, i] = 2.0 + x[i]
        k[0, 1] = k[1, 0] = 0.5 * x[1]
        return k

    kappa = disc.interpolate_kappa(tensor)
    assert max(_frozen_gap(disc.system_at(kappa), disc, kappa)) < 1e-14


def test_system_at_keeps_the_couplings_of_a_high_contrast_kappa():
    """Geometric zeros are dropped relative to each entry's own diagonals, not to the
    largest entry: at a contrast of 1e-20 the weak region's couplings stay (relative to
    the largest entry they would all be 'zero'), and the right triangles' cancellations go,
    as the kappa map drops them."""
    disc = pf.discretize(pf.unit_square(8), element="P1", kappa_space="P0")
    centroids = disc.mesh.p[:, disc.mesh.t].mean(axis=1)
    kappa = np.where(centroids[0] < 0.5, 1.0, 1e-20)
    A = disc.system_at(kappa).operator(jnp.ones(1)).to_scipy()
    reference = disc.stiffness_matrix(kappa)
    assert A.nnz == reference.nnz == len(disc.pattern[0])
    weak = np.flatnonzero(disc.basis.doflocs[0, disc.free_dofs] > 0.6)
    block, expected = A[weak][:, weak].toarray(), reference[weak][:, weak].toarray()
    assert np.count_nonzero(block) > 3 * len(weak)  # the weak region's off-diagonals
    np.testing.assert_allclose(block, expected, rtol=1e-13, atol=0.0)


def test_a_source_inversion_builds_no_kappa_map():
    """A source inversion freezes the system at its kappa: the map G is never built, and the
    loss and gradient are the kappa map's."""
    disc = pf.discretize(pf.unit_square(6), element="P1", kappa_space="P1",
                         dirichlet=lambda x: x[0])
    kappa = 1.0 + disc.kappa_basis.doflocs[1]
    obs = pf.full_field(disc, u_true=disc.interpolate(lambda x: np.sin(3 * x[0]) * x[1]))
    problem = pf.inverse_problem(disc, obs, unknown="source", alpha=1e-4, known=kappa)
    assert "_maps" not in disc.__dict__ and problem.known.shape == (1,)
    solver = pf.TruncatedCG(7, "jacobi")
    z = jnp.asarray(np.cos(np.arange(problem.n_parameters)))

    @jax.jit  # one compile per problem structure, not one per eager operation
    def value_and_grad(p):
        return jax.value_and_grad(lambda z: p.loss(z, solver)[0])(z)

    mapped = dataclasses.replace(problem, system=disc.system, known=jnp.asarray(kappa))
    (value, grad), (value_ref, grad_ref) = value_and_grad(problem), value_and_grad(mapped)
    assert abs(value - value_ref) <= 1e-13 * abs(value_ref)
    np.testing.assert_allclose(grad, grad_ref, rtol=0, atol=1e-12 * np.abs(grad_ref).max())


def test_system_at_refuses_a_traced_or_bad_kappa_and_takes_only_its_scale():
    disc = pf.discretize(pf.unit_square(3), element="P1")
    with pytest.raises(pf.CoefficientError, match="kappa: traced"):
        jax.jit(disc.system_at)(jnp.ones(disc.n_kappa))
    with pytest.raises(pf.CoefficientError, match=r"kappa: .*> 0"):
        disc.system_at(-np.ones(disc.n_kappa))
    with pytest.raises(pf.CoefficientError, match=r"known: .*> 0"):
        disc.host_system_at(np.zeros(disc.n_kappa), name="known")
    # a whole field where the frozen system takes its scale: named, never kappa[0] A
    frozen, kappa = disc.system_at(np.ones(disc.n_kappa)), jnp.full(disc.n_kappa, 2.0)
    for call in (frozen.operator, frozen.rhs, jax.jit(frozen.operator),
                 lambda k: frozen.solve(k, None, pf.TruncatedCG(2))):
        with pytest.raises(pf.ShapeError, match=r"frozen at one kappa.*jnp.ones\(1\)"):
            call(kappa)


def test_system_at_a_pure_neumann_problem_carries_its_nullspace():
    disc = pf.discretize(pf.unit_square(4), element="P1", kappa_space="P1", dirichlet=None)
    kappa = 1.0 + disc.kappa_basis.doflocs[0]
    frozen = disc.system_at(kappa)
    assert frozen.lifting.shape == (0, 1) and frozen.nullspace is not None
    np.testing.assert_array_equal(frozen.nullspace, disc.system.nullspace)
    assert max(_frozen_gap(frozen, disc, kappa)) < 1e-14
    f = disc.balance_source(np.cos(np.arange(disc.n_dofs)))
    x = frozen.solve(jnp.ones(1), jnp.asarray(f), pf.ConvergedCG(rtol=1e-12)).x
    x_ref = disc.system.solve(jnp.asarray(kappa), jnp.asarray(f), pf.ConvergedCG(rtol=1e-12)).x
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-10 * np.abs(x_ref).max())


def test_the_system_first_read_inside_jit_is_built_eagerly():
    """``disc.system`` is cached on first read; read first inside ``jax.jit`` it was built of
    tracers (its matrices are put on the device), which leaked out of the trace and broke
    every later use of the discretisation."""
    disc = pf.discretize(pf.unit_square(4), element="P1")
    kappa = np.linspace(1.0, 2.0, disc.n_kappa)
    inside = jax.jit(lambda k: disc.system.rhs(k))(jnp.asarray(kappa))
    np.testing.assert_allclose(inside, disc.rhs(kappa), atol=1e-13)
    op = disc.system.operator(jnp.asarray(kappa))  # outside the trace, after it
    assert abs(op.to_scipy() - disc.stiffness_matrix(kappa)).max() < 1e-13


@pytest.mark.parametrize("size", [0, 1, 7, 5000])
def test_the_assembly_keys_dedupe_as_numpy_unique(size):
    """The fast dedupe of assembled (row, col) keys gives np.unique's keys and inverse, on
    element-ordered runs with duplicates and on shuffled keys."""
    rng = np.random.default_rng(size)
    runs = np.sort(rng.integers(0, max(size // 3, 1), size))
    for keys in (runs, rng.permutation(runs), rng.integers(-50, 50, size)):
        unique, inverse = unique_with_inverse(keys.astype(np.int64))
        expected, expected_inverse = np.unique(keys, return_inverse=True)
        np.testing.assert_array_equal(unique, expected)
        np.testing.assert_array_equal(inverse, expected_inverse.ravel())
        np.testing.assert_array_equal(unique[inverse], keys)


def test_dirichlet_per_tag_and_neumann(manufactured_2d):
    """Dirichlet on left/right (callable and constant-free), Neumann flux on top/bottom."""
    m = manufactured_2d

    def flux(sign, axis):
        return lambda x: sign * m.kappa(x) * m.grad_u(x)[axis]

    errors = []
    for n in (8, 16, 32):
        disc = pf.discretize(pf.unit_square(n), element="P2", kappa_space="P1",
                             dirichlet={"left": m.u, "right": m.u},
                             neumann={"top": flux(1, 1), "bottom": flux(-1, 1)})
        kappa = disc.interpolate_kappa(m.kappa)
        x = pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, disc.interpolate(m.f))).x
        errors.append(pf.fem.l2_error(disc, disc.expand(x), m.u))
    rates = np.log2(np.array(errors[:-1]) / errors[1:])
    assert rates[-1] == pytest.approx(3.0, abs=0.15)


def test_unknown_boundary_and_element_are_named():
    mesh = pf.unit_square(2)
    with pytest.raises(pf.errors.DiscretizationError, match=r"unknown boundary 'inlet'.*'left'"):
        pf.discretize(mesh, dirichlet={"inlet": 0.0})
    with pytest.raises(pf.errors.DiscretizationError, match=r"element='P3'.*expected one of"):
        pf.discretize(mesh, element="P3")
    with pytest.raises(pf.errors.DiscretizationError, match="kappa_space='P3'"):
        pf.discretize(mesh, kappa_space="P3")
    with pytest.raises(pf.DataError, match="NaN/Inf"):
        pf.discretize(mesh, dirichlet=lambda x: np.nan * x[0])


def test_source_map_is_the_mass_matrix(small_problem):
    disc, kappa, f = small_problem
    b_f = disc.system.rhs(kappa, f) - disc.system.rhs(kappa)
    np.testing.assert_allclose(b_f, (disc.mass_matrix @ f)[disc.free_dofs], atol=1e-14)
    # mass matrix integrates constants to the area, laplace matrix annihilates them
    ones = np.ones(disc.n_dofs)
    assert ones @ disc.mass_matrix @ ones == pytest.approx(1.0)
    assert abs(disc.laplace_matrix @ ones).max() < 1e-12


def convergence_rates(meshes, element, manufactured, solve=pf.direct_solve):
    """The last L2 and H1 rates. The system is assembled at kappa in one pass (the same
    operator and right-hand side as the kappa map's: test_system_at_kappa_equals_the_kappa_map_
    there) and solved by sparse LU (pyamg's CG took three times as long on the P2
    tetrahedra); ``solve=`` takes another solver, for meshes too big for LU."""
    m = manufactured
    errors = []
    for mesh in meshes:
        disc = pf.discretize(mesh, element=element, kappa_space="P1", dirichlet=m.u)
        A, b = disc.host_system_at(disc.interpolate_kappa(m.kappa), disc.interpolate(m.f))
        x = solve(A, b).x
        full = disc.expand(x)
        errors.append((pf.fem.l2_error(disc, full, m.u), pf.fem.h1_error(disc, full, m.grad_u)))
    errors = np.array(errors)
    return np.log2(errors[:-1] / errors[1:])[-1]


EXPECTED = {"P1": (2.0, 1.0), "Q1": (2.0, 1.0), "P2": (3.0, 2.0)}


@pytest.mark.parametrize(("name", "make", "element"), [
    ("square P1", lambda r: pf.unit_square(4 * 2**r), "P1"),
    ("square P2", lambda r: pf.unit_square(4 * 2**r), "P2"),
    ("square Q1", lambda r: pf.unit_square(4 * 2**r, "quad"), "Q1"),
    ("L-shape P1", lambda r: pf.l_shape(r + 2), "P1"),
    ("cube P1", lambda r: pf.unit_cube(4 * 2**r), "P1"),
    ("cube P2", lambda r: pf.unit_cube(2 * 2**r), "P2"),
])
def test_rates_on_generated_meshes(name, make, element, manufactured_2d, manufactured_3d):
    meshes = [make(r) for r in range(3)]
    manufactured = manufactured_3d if meshes[0].dim() == 3 else manufactured_2d
    l2_rate, h1_rate = convergence_rates(meshes, element, manufactured)
    assert l2_rate == pytest.approx(EXPECTED[element][0], abs=0.15), name
    assert h1_rate == pytest.approx(EXPECTED[element][1], abs=0.15), name


@pytest.mark.parametrize(("filename", "element", "levels"), [
    ("square_tri.msh", "P1", 3), ("square_tri.msh", "P2", 3), ("plate_hole.msh", "P1", 3),
    ("plate_hole.msh", "P2", 2), ("square_quad.msh", "Q1", 3),
    # P2 on tetrahedra: the generated cube's P2 rates run by default
    pytest.param("cube_tet.msh", "P2", 2, marks=pytest.mark.slow),
])
def test_rates_on_shipped_meshes(filename, element, levels, manufactured_2d, manufactured_3d):
    base = pf.load_mesh(MESH_DIR / filename)
    manufactured = manufactured_3d if base.dim() == 3 else manufactured_2d
    l2_rate, h1_rate = convergence_rates([base.refined(r) for r in range(levels)], element,
                                         manufactured)
    assert l2_rate == pytest.approx(EXPECTED[element][0], abs=0.15)
    assert h1_rate == pytest.approx(EXPECTED[element][1], abs=0.15)


@pytest.mark.slow
def test_rates_on_fine_tetrahedra_p1(manufactured_3d):
    """P1 on 8^3 .. 32^3 cubes (200k cells at the finest). Not on refined shipped tetrahedra:
    scikit-fem's uniform refinement halves their minimum shape quality per level."""
    l2_rate, h1_rate = convergence_rates([pf.unit_cube(n) for n in (8, 16, 32)], "P1",
                                         manufactured_3d,
                                         solve=lambda A, b: pf.amg_solve(A, b, rtol=1e-12))
    assert l2_rate == pytest.approx(2.0, abs=0.1)
    assert h1_rate == pytest.approx(1.0, abs=0.05)


def test_rhs_follows_the_dirichlet_data_leaf():
    """Changing g in the LinearSystem pytree equals re-discretising with that data."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    mesh = pf.unit_square(6)
    once = pf.discretize(mesh, element="P2", kappa_space="P1", dirichlet=lambda x: x[0] + x[1])
    twice = pf.discretize(mesh, element="P2", kappa_space="P1",
                          dirichlet=lambda x: 2 * (x[0] + x[1]))
    kappa = jnp.asarray(once.interpolate_kappa(lambda x: 1 + x[1]))
    system = dataclasses.replace(once.system,
                                 dirichlet_values=2 * once.system.dirichlet_values)
    np.testing.assert_allclose(system.rhs(kappa), twice.system.rhs(kappa), atol=1e-13)
    np.testing.assert_allclose(twice.rhs(np.asarray(kappa)), twice.system.rhs(kappa),
                               atol=1e-13)
    # b is linear in g: the derivative along g is b(g) - b(0)
    def rhs_of(g):
        return dataclasses.replace(once.system, dirichlet_values=g).rhs(kappa)

    g = once.system.dirichlet_values
    _, tangent = jax.jvp(rhs_of, (g,), (g,))
    np.testing.assert_allclose(tangent, rhs_of(g) - rhs_of(0 * g), atol=1e-13)


def test_a_pinned_pure_neumann_problem_is_the_balanced_solution_shifted():
    """A pin at a vertex fixes the constant a pure Neumann problem leaves free: the pinned
    state is the nullspace-projected one shifted to the pinned value there. A point that is
    no vertex, or a malformed pin, is refused by name."""
    def flux(x):
        return (x[0] - 0.5) * x[1] * (x[1] - 1.0)
    sides = {side: flux for side in ("left", "right", "bottom", "top")}
    mesh = pf.unit_square(8)
    free = pf.discretize(mesh, element="P2", dirichlet=None, neumann=sides)
    pinned = pf.discretize(mesh, element="P2", dirichlet=None, neumann=sides,
                           pins=[((0.5, 0.5), 0.25)])
    kappa = free.interpolate_kappa(lambda x: 1.0 + x[0])
    A, b = free.host_system_at(kappa)
    u_free = pf.linalg.solve(pf.SparseMatrix.from_scipy(A), b, pf.ConvergedCG(rtol=1e-13),
                             nullspace=free.nullspace).x
    u_pin = pf.direct_solve(*pinned.host_system_at(kappa)).x
    centre = int(pinned.dirichlet_dofs[0])
    u_pin_full = pinned.expand(u_pin)
    np.testing.assert_allclose(u_pin_full, free.expand(u_free) - free.expand(u_free)[centre]
                               + 0.25, atol=1e-9)
    with pytest.raises(pf.errors.DiscretizationError, match=r"pins\[0\]: point \[0.51, 0.5\] "
                       r"is not a node of the mesh \(nearest dof location \[0.5, 0.5\]"):
        pf.discretize(mesh, dirichlet=None, pins=[((0.51, 0.5), 0.0)])
    with pytest.raises(pf.errors.DiscretizationError, match=r"pins\[0\] = .*expected a finite"):
        pf.discretize(mesh, dirichlet=None, pins=[((0.5,), 0.0)])


@pytest.mark.parametrize("element, kappa_space, mesh", [
    ("P1", "P1", lambda: pf.unit_cube(4)), ("P2", "P1", lambda: pf.unit_square(6)),
    ("Q1", "P0", lambda: pf.unit_square(5, "quad"))])
def test_assembly_in_passes_gives_the_maps_of_one_pass(monkeypatch, element, kappa_space, mesh):
    """Big meshes assemble kappa -> A in passes over their elements (bounded memory): a
    pass of a few elements at a time sums to the same maps and patterns."""
    import prdp_fem.fem.discretization as discretization

    def maps():
        disc = pf.discretize(mesh(), element=element, kappa_space=kappa_space,
                             dirichlet={"left": 0.0})
        return disc.assembly, disc.pattern, disc.lifting_assembly, disc.lifting_pattern

    whole = maps()
    monkeypatch.setattr(discretization, "_ENTRIES_PER_PASS", 200)
    passes = maps()
    for one, many in ((whole[0], passes[0]), (whole[2], passes[2])):
        assert one.shape == many.shape and one.nnz == many.nnz
        assert abs(one - many).max() <= 1e-15 * abs(one).max()
    for one, many in zip(whole[1] + whole[3], passes[1] + passes[3], strict=True):
        np.testing.assert_array_equal(one, many)
