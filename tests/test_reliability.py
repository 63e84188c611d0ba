"""One writer per output directory, outputs inside the directory the user chose, shapes
checked at the system's entry (issue: reliability)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL_STUDY

from prdp_fem.atomic import atomic_path
from prdp_fem.errors import OutputLockedError, SceneError, ShapeError
from prdp_fem.lock import directory_lock
from prdp_fem.scene import parse_scene

ROOT = Path(__file__).resolve().parent.parent


def cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-c", "from prdp_fem.cli import run; run()",
                           *map(str, args)], capture_output=True, text=True, timeout=300,
                          cwd=cwd, env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_a_second_writer_is_refused_with_the_holders_pid(tmp_path):
    """This process holds the directory; a study in another process exits 2 at once, in one
    line naming the directory and this pid, and writes nothing there."""
    scene = tmp_path / "small.toml"
    scene.write_text(SMALL_STUDY.replace("STEPS", "3"))
    out = tmp_path / "out"
    out.mkdir()
    # a bench prdp run to resume there, with the options the command below gives
    (out / "bench.json").write_text(json.dumps({"scene": ["mother"], "steps": None,
                                                "repeats": 1, "seeds": None}))
    with directory_lock(out):
        for args in (("study", scene, "--out", out), ("study", scene, "--out", out, "--resume"),
                     ("bench", "prdp", "--scene", "mother", "--out", out, "--resume")):
            done = cli(*args)
            assert done.returncode == 2, done.stderr
            assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
            assert f"(pid {os.getpid()})" in done.stderr and str(out) in done.stderr
        assert sorted(p.name for p in out.iterdir()) == [".prdp-fem.lock", "bench.json"]
    (out / "bench.json").unlink()
    # released with the block (and by the kernel when a holder dies): the study runs now
    done = cli("study", scene, "--out", out)
    assert done.returncode == 0, done.stderr
    assert (out / "summary.csv").exists()


def test_the_lock_is_released_when_its_holder_is_killed(tmp_path):
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from prdp_fem.lock import directory_lock\n"
         f"with directory_lock({str(tmp_path)!r}):\n print('held', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputLockedError, match=f"pid {holder.pid}"), \
                directory_lock(tmp_path):
            pass
    finally:
        holder.kill()
        holder.wait()
    with directory_lock(tmp_path):  # kill -9 left no stale lock
        pass


def test_temporary_files_are_unique_per_writer(tmp_path):
    target = tmp_path / "summary.csv"
    with atomic_path(target) as first, atomic_path(target) as second:
        assert first != second and first.parent == second.parent == tmp_path
        first.write_text("a")
        second.write_text("b")
    assert target.read_text() == "a" and sorted(p.name for p in tmp_path.iterdir()) == [
        "summary.csv"]


@pytest.mark.parametrize("name", ["../../../x", "a/b", "..", ".", "a\\b", "x\0y"])
def test_a_scene_name_cannot_leave_the_working_directory(name):
    with pytest.raises(SceneError, match=r"name = .*usable as a file name"):
        parse_scene({"name": name})


def test_the_cli_writes_nothing_outside_for_an_escaping_name(tmp_path):
    work = tmp_path / "deep" / "work"
    work.mkdir(parents=True)
    (work / "evil.toml").write_text('name = "../../escaped"\n[mesh]\nn = 4\n')
    for command in ("invert", "solve"):
        done = cli(command, "evil.toml", cwd=work)
        assert done.returncode == 2 and "usable as a file name" in done.stderr
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["deep", "evil.toml", "work"]


@pytest.mark.parametrize("frozen", [False, True])
def test_rhs_refuses_a_source_of_the_wrong_length(small_problem, frozen):
    disc, kappa, f = small_problem
    system = disc.system_at(kappa) if frozen else disc.system
    k = jnp.ones(1) if frozen else jnp.asarray(kappa)
    for bad in (f[:-1], np.concatenate([f, [0.0]]), np.ones((2, f.size))):
        with pytest.raises(ShapeError, match=rf"f: a nodal source of {f.size} values"):
            system.rhs(k, bad)
        with pytest.raises(ShapeError):  # under jit too: the shape is static
            jax.jit(system.rhs)(k, jnp.asarray(bad))
    # the right length still gives the host assembly's right-hand side
    np.testing.assert_allclose(system.rhs(k, f), disc.rhs(kappa, f), rtol=1e-12, atol=1e-12)
