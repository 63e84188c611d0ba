"""One linear system over several devices (prdp_fem.linalg.sharding, linalg.halo).

Several devices need JAX started with them (host devices forced by ``XLA_FLAGS``), so those
checks run in processes of their own: the shipped example on a 2-D mesh file (its 3-D mesh
file, the internals in tests/sharded_checks.py and two processes joined by
``jax.distributed`` are slow-marked). This process has one device: the partition's
bookkeeping and the refusals are checked here.
"""

import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import prdp_fem as pf
from prdp_fem.errors import ShapeError, SolverConfigError
from prdp_fem.linalg import partition, shard

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "sharded_inversion.py"
TOLERANCE = 1e-12


def json_lines(*command: str) -> list[dict]:
    done = subprocess.run([sys.executable, *command], capture_output=True, text=True,
                          timeout=600, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def assert_equal_to_one_device(result: dict) -> None:
    gaps = {name: value for name, value in result.items()
            if name.startswith(("solve", "gradient", "inversion"))}
    assert len(gaps) == 6, gaps
    assert max(gaps.values()) <= TOLERANCE, gaps
    assert result["iterations equal"]


@pytest.mark.parametrize("mesh", ["plate_hole.msh",
                                  pytest.param("cube_tet.msh", marks=pytest.mark.slow)])
def test_sharded_solves_gradients_and_inversion_equal_one_device_on_mesh_files(mesh):
    results = json_lines(str(EXAMPLE), str(ROOT / "meshes" / mesh), "--refine", "0", "--json")
    assert [r["mesh"] for r in results] == [mesh]
    for result in results:
        assert result["devices"] == 4 and result["dofs"] > 4 * 16
        assert_equal_to_one_device(result)


@pytest.mark.slow
def test_sharded_internals_on_four_devices():
    (out,) = json_lines(str(ROOT / "tests" / "sharded_checks.py"))
    # a reverse Cuthill-McKee block couples to its two neighbours, through a thin halo
    assert out["shifts rcm"] == [1, -1]
    assert max(out["halo rcm"]) <= 2 * int(np.sqrt(out["n"])) + 2
    assert out["shifts scattered"] == [1, 2, -1]  # random parts: every other device
    gaps = {k: v for k, v in out.items() if isinstance(v, float)}
    assert len(gaps) == 10 and max(gaps.values()) <= TOLERANCE, gaps


@pytest.mark.slow
def test_two_processes_joined_by_jax_distributed_equal_one_device():
    results = json_lines(str(EXAMPLE), "--processes", "2", "--json")
    assert sorted(r["mesh"] for r in results) == ["cube_tet.msh"] * 2 + ["plate_hole.msh"] * 2
    for result in results:
        assert result["processes"] == 2 and result["devices"] == 4
        assert_equal_to_one_device(result)


@pytest.fixture(scope="module")
def operator():
    disc = pf.discretize(pf.unit_square(9), element="P1", kappa_space="P1", dirichlet=0.0)
    kappa = jnp.asarray(np.exp(disc.interpolate_kappa(lambda x: x[0] * x[1])))
    return disc.system.operator(kappa), disc.system.rhs(kappa, jnp.ones(disc.n_dofs))


def one_device_mesh(*names):
    return jax.make_mesh((1,) * len(names), names)


def test_partition_numbers_every_unknown_once_part_by_part(operator):
    A, _ = operator
    n = A.shape[0]
    part = partition(np.asarray(A.rows), np.asarray(A.cols), n, one_device_mesh("x"),
                     parts=np.zeros(n, int))
    position, gather = np.asarray(part.position), np.asarray(part.gather)
    np.testing.assert_array_equal(gather[position], np.arange(n))
    assert part.n_padded == n and part.halo.shifts == ()
    # the renumbered pattern holds the same matrix
    renumbered = part.partitioned(A)
    dense = np.zeros((n, n))
    np.add.at(dense, (np.asarray(renumbered.rows), np.asarray(renumbered.cols)),
              np.asarray(renumbered.values))
    np.testing.assert_allclose(dense[np.ix_(position, position)], np.asarray(A.todense()))


def test_one_device_shard_solves_as_the_plain_matrix(operator):
    A, b = operator
    sharded = shard(A, one_device_mesh("x"))
    for solver in (pf.TruncatedCG(12), pf.TruncatedCG(12, gradient="unrolled"),
                   pf.ConvergedCG(rtol=1e-10)):
        np.testing.assert_allclose(pf.solve(sharded, b, solver).x, pf.solve(A, b, solver).x,
                                   rtol=1e-13, atol=1e-16)


def test_shard_refuses_bad_meshes_parts_and_preconditioners(operator):
    A, b = operator
    n = A.shape[0]
    with pytest.raises(SolverConfigError, match=r"jax\.sharding\.Mesh"):
        shard(A, "cpu")
    with pytest.raises(SolverConfigError, match="name the one"):
        shard(A, one_device_mesh("a", "b"))
    with pytest.raises(SolverConfigError, match="one of the mesh's axes"):
        shard(A, one_device_mesh("a"), axis="b")
    with pytest.raises(ShapeError, match=r"expected parts 0 \.\. 0, one per device"):
        shard(A, one_device_mesh("x"), parts=np.arange(n) % 2)
    with pytest.raises(ShapeError, match=f"one integer part per unknown \\({n}\\)"):
        shard(A, one_device_mesh("x"), parts=np.zeros(3, int))
    with pytest.raises(ShapeError, match="expected a square one"):
        shard(pf.linalg.SparseMatrix.from_coo([0], [1], [1.0], (1, 2)), one_device_mesh("x"))
    amg = pf.TruncatedCG(5, preconditioner=pf.amg_preconditioner(A))
    with pytest.raises(SolverConfigError, match="'jacobi' or 'identity'"):
        pf.solve(shard(A, one_device_mesh("x")), b, amg)
