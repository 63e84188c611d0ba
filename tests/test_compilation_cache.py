"""The persistent compilation cache: where it goes, how it is switched off, and that a second
process loads the executables the first one compiled (counted by JAX's own cache events)."""

from conftest import json_from_a_process

from prdp_fem.compilation_cache import cache_directory

SCRIPT = """
import json, jax, jax.numpy as jnp, numpy as np
events = []
jax.monitoring.register_event_listener(lambda name, **_: events.append(name))
import prdp_fem as pf
imported_with = jax.config.jax_compilation_cache_dir  # the import switches nothing on
pf.enable_compilation_cache()
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)  # store even quick ones
disc = pf.discretize(pf.unit_square(9))
solve = jax.jit(lambda kappa, system: system.solve(
    kappa, None, pf.TruncatedCG(5, gradient="implicit")).x)
x = solve(jnp.ones(disc.n_kappa), disc.system)
print(json.dumps({"directory": jax.config.jax_compilation_cache_dir,
                  "at_import": imported_with,
                  "hits": events.count("/jax/compilation_cache/cache_hits"),
                  "misses": events.count("/jax/compilation_cache/cache_misses"),
                  "finite": bool(np.isfinite(np.asarray(x)).all())}))
"""


def _run(setting: str) -> dict:
    return json_from_a_process(SCRIPT, setting)


def test_directory_from_the_environment(tmp_path):
    assert cache_directory({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "prdp_fem" / "jax"
    assert cache_directory({"PRDP_FEM_COMPILATION_CACHE": str(tmp_path / "c")}) == tmp_path / "c"
    for off in ("0", "off", "False", " "):
        assert cache_directory({"PRDP_FEM_COMPILATION_CACHE": off}) is None
    for on in ("1", "on", "True", " yes"):  # the default directory, not one named "1"
        assert cache_directory({"PRDP_FEM_COMPILATION_CACHE": on,
                                "XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "prdp_fem" / "jax"


def test_second_process_loads_the_compiled_solve(tmp_path):
    first = _run(str(tmp_path))
    assert first["directory"] == str(tmp_path) and first["finite"]
    assert not first["at_import"]
    assert first["hits"] == 0 and first["misses"] > 0
    assert any(tmp_path.iterdir())  # executables were written
    second = _run(str(tmp_path))
    assert second["misses"] == 0 and second["hits"] == first["misses"]


def test_switched_off_writes_nothing(tmp_path):
    run = _run("0")
    assert not run["directory"] and run["hits"] == 0 and run["misses"] == 0
