"""One inversion spread over several devices, checked against the same run on one device.

A log-kappa inversion on each mesh file (refined ``--refine`` times; P1 state and
coefficient, u = 0 on the boundary, unit source, the state observed in full with 1 % noise,
H1 regulariser) run twice in one process:
on one device, and with its state's free dofs spread over the devices of a
``jax.sharding.Mesh`` (``problem.sharded(mesh)``). Printed: the largest relative difference
of the solves (truncated CG in both gradient modes, converged CG), of the gradients through
them, and of the parameters after a short PRDP inversion. Without accelerators, host devices
are forced (``--devices``, set before JAX starts). With ``--processes P`` it starts ``P``
processes on this machine joined by ``jax.distributed.initialize``, each holding
``devices / P`` of the mesh's devices: the multi-host path, as one machine runs it (on a
cluster, start this script once per host with ``--coordinator HOST:PORT --processes P
--process-id I``).

    python examples/sharded_inversion.py [MESH ...] [--devices 4] [--refine 1] [--processes 2]
"""

import argparse
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

MESHES = Path(__file__).resolve().parent.parent / "meshes"
STEPS = 6
K = 20


def problem_on(mesh_file: Path, refine: int = 0):
    import logging

    import numpy as np

    import prdp_fem as pf
    from prdp_fem.fem import full_field, with_noise
    from prdp_fem.inverse import inverse_problem

    # u = 0 on the whole boundary: the boundary names that refining drops are not needed
    logging.getLogger("skfem").setLevel(logging.ERROR)
    disc = pf.discretize(pf.load_mesh(mesh_file).refined(refine), element="P1",
                         kappa_space="P1", dirichlet=0.0)
    m_true = disc.interpolate_kappa(lambda x: 0.5 * np.sin(np.pi * x[0]) * np.cos(np.pi * x[1]))
    f = np.ones(disc.n_dofs)
    kappa = np.exp(m_true)
    u = disc.expand(pf.direct_solve(disc.stiffness_matrix(kappa), disc.rhs(kappa, f)).x)
    data = with_noise(full_field(disc, u_true=u), 0.01, seed=0)
    return inverse_problem(disc, data, unknown="log_kappa", alpha=1e-6, regularization="h1",
                           known=f, truth=m_true)


def differences(problem, sharded) -> dict:
    """Largest relative differences, sharded against one device."""
    import jax
    import numpy as np

    import prdp_fem as pf
    from prdp_fem.inverse import invert, prdp

    def host(array):  # a replicated result: every process holds all of it
        return np.asarray(array.addressable_data(0))

    def gap(got, want):
        want = host(want)
        return float(np.max(np.abs(host(got) - want)) / np.max(np.abs(want)))

    z = 0.3 * jax.numpy.ones(problem.n_parameters)
    solvers = {"truncated implicit": pf.TruncatedCG(K),
               "truncated unrolled": pf.TruncatedCG(K, gradient="unrolled"),
               "converged": pf.ConvergedCG(rtol=1e-10)}
    result = {"dofs": problem.system.n_free,
              "devices": sharded.system.layout.mesh.size}
    for name, solver in solvers.items():
        result[f"solve {name}"] = gap(sharded.state(z, solver).x, problem.state(z, solver).x)
        if name == "converged":
            continue
        grad = jax.jit(jax.grad(lambda z, p, solver=solver: p.loss(z, solver)[0]))
        result[f"gradient {name}"] = gap(grad(z, sharded), grad(z, problem))
    runs = [invert(p, refinement=prdp(K0=5, dK=5), steps=STEPS) for p in (problem, sharded)]
    result["inversion"] = gap(runs[1].params, runs[0].params)
    result["iterations equal"] = [r.iterations for r in runs[0].history] == [
        r.iterations for r in runs[1].history]
    return result


def run(mesh_files: list[Path], devices: int, refine: int = 0, coordinator: str | None = None,
        processes: int = 1, process_id: int = 0) -> list[dict]:
    """The comparison on each mesh file in this process (JAX not started yet)."""
    local = devices // processes
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={local}"
    import jax

    if processes > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(coordinator, num_processes=processes,
                                   process_id=process_id)
    mesh = jax.make_mesh((devices,), ("dofs",))
    results = []
    for mesh_file in mesh_files:
        problem = problem_on(mesh_file, refine)
        results.append({**differences(problem, problem.sharded(mesh)), "mesh": mesh_file.name,
                        "processes": processes})
    return results


def spawn(mesh_files: list[Path], devices: int, refine: int, processes: int) -> list[dict]:
    """This script in ``processes`` local processes joined by ``jax.distributed``: the
    results of every process."""
    with socket.socket() as probe:  # a free port for the coordinator
        probe.bind(("localhost", 0))
        port = probe.getsockname()[1]
    commands = [[sys.executable, __file__, *map(str, mesh_files), "--devices", str(devices),
                 "--refine", str(refine),
                 "--processes", str(processes), "--process-id", str(i), "--coordinator",
                 f"localhost:{port}", "--json"] for i in range(processes)]
    running = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
               for c in commands]
    results = []
    for process in running:
        out, err = process.communicate(timeout=600)
        if process.returncode:
            raise RuntimeError(f"process exited with {process.returncode}: {err[-2000:]}")
        results += [json.loads(line) for line in out.strip().splitlines()
                    if line.startswith("{")]
    return results


def main(argv=()):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*", type=Path,
                        default=[MESHES / "plate_hole.msh", MESHES / "cube_tet.msh"])
    parser.add_argument("--devices", type=int, default=4)
    parser.add_argument("--refine", type=int, default=1, help="uniform refinements")
    parser.add_argument("--processes", type=int, default=1)
    parser.add_argument("--process-id", type=int)
    parser.add_argument("--coordinator")
    parser.add_argument("--json", action="store_true", help="one JSON line per process")
    args = parser.parse_args(argv)
    if args.devices % args.processes:
        parser.error("--devices must be a multiple of --processes")
    if args.processes > 1 and args.process_id is None:
        results = spawn(args.meshes, args.devices, args.refine, args.processes)
    else:
        results = run(args.meshes, args.devices, args.refine, args.coordinator,
                      args.processes, args.process_id or 0)
    for result in results:
        if args.json:
            print(json.dumps(result))
            continue
        print(f"{result['mesh']}: {result['dofs']} free dofs over {result['devices']} devices "
              f"in {result['processes']} process(es); relative difference to one device:")
        for name, value in result.items():
            if name.startswith(("solve", "gradient", "inversion")):
                print(f"  {name:<28} {value:.1e}")
        print(f"  PRDP's iteration counts equal: {result['iterations equal']}")
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
