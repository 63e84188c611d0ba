"""Checks of prdp_fem.linalg.sharding on 4 forced host devices, run by test_sharding.py in a
process of its own (the device count is read when JAX starts): one JSON line of results."""

import json
import os

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_force_host_platform_device_count=4")

import jax
import jax.numpy as jnp
import numpy as np

import prdp_fem as pf
from prdp_fem.linalg import jacobi_solve, matvec, shard


def gap(got, want) -> float:
    want = np.asarray(want)
    return float(np.max(np.abs(np.asarray(got) - want)) / np.max(np.abs(want)))


def main() -> dict:
    mesh = jax.make_mesh((4,), ("x",))
    disc = pf.discretize(pf.unit_square(20), element="P1", kappa_space="P1", dirichlet=0.0)
    kappa = jnp.asarray(np.exp(disc.interpolate_kappa(lambda x: np.sin(3 * x[0]) * x[1])))
    A = disc.system.operator(kappa)
    b = disc.system.rhs(kappa, jnp.ones(disc.n_dofs))
    n = A.shape[0]
    out = {"n": n}
    # random parts: every device reads from every other (shifts 1, 2 and -1)
    parts = np.random.default_rng(0).integers(0, 4, n)
    rcm, scattered = shard(A, mesh), shard(A, mesh, parts=parts)
    out["shifts rcm"] = list(rcm.layout.halo.shifts)
    out["shifts scattered"] = list(scattered.layout.halo.shifts)
    out["halo rcm"] = [int(s.shape[0]) // 4 for s in rcm.layout.halo.sends]
    solver = pf.TruncatedCG(25)
    reference = pf.solve(A, b, solver).x
    for name, sharded in (("rcm", rcm), ("scattered", scattered)):
        out[f"matvec {name}"] = gap(matvec(sharded, b), matvec(A, b))
        out[f"solve {name}"] = gap(pf.solve(sharded, b, solver).x, reference)
    # the values' derivative through a product and through an implicit solve
    x = reference

    def through_product(values, matrix):
        return jnp.sum(matvec(matrix.with_values(values), x) ** 2)

    def through_solve(values, matrix):
        return jnp.sum(pf.solve(matrix.with_values(values), b, solver).x ** 2)

    for name, f in (("product", through_product), ("solve", through_solve)):
        grad = jax.jit(jax.grad(f))
        out[f"values gradient {name}"] = gap(grad(A.values, scattered), grad(A.values, A))
    batch = jnp.stack([b, 2 * b, jnp.roll(b, 7)])
    batched = jax.vmap(lambda v: pf.solve(rcm, v, solver).x)(batch)
    out["vmap"] = gap(batched, jax.vmap(lambda v: pf.solve(A, v, solver).x)(batch))
    sweeps = pf.TruncatedJacobi(30)
    out["stationary jacobi"] = gap(jacobi_solve(rcm, b, sweeps).x, jacobi_solve(A, b, sweeps).x)
    # pure Neumann: the constants are the nullspace
    neumann = pf.discretize(pf.unit_square(12), element="P1", kappa_space="P1")
    system = neumann.system
    ones = jnp.ones(system.n_kappa)
    f = jnp.asarray(neumann.interpolate(lambda p: np.cos(np.pi * p[0])))
    out["nullspace"] = gap(system.sharded(mesh).solve(ones, f, pf.ConvergedCG(rtol=1e-10)).x,
                           system.solve(ones, f, pf.ConvergedCG(rtol=1e-10)).x)
    two_axes = jax.make_mesh((2, 2), ("a", "b"))
    out["two axes"] = gap(pf.solve(shard(A, two_axes, axis="b"), b, solver).x, reference)
    return out


if __name__ == "__main__":
    print(json.dumps(main()))
