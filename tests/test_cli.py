"""The prdp-fem command: the forward study, exit codes and one-line errors."""

import gc
import json
import sys

import pytest

from prdp_fem.cli.main import main, run


def test_forward_study_writes_records(tmp_path, capsys):
    out = tmp_path / "forward.jsonl"
    status = main(["forward", "--n", "16", "--iterations", "0", "20", "400", "--out", str(out)])
    assert status == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["requested_iterations"] for r in records] == [0, 20, 400]
    assert records[0]["relative_l2_error"] == pytest.approx(1.0)
    assert records[1]["relative_l2_error"] < 1.0
    assert records[2]["relative_l2_error"] < 1e-10
    assert records[2]["iterations"] < 400  # converged to round-off and stopped
    assert "first-solve compile" in capsys.readouterr().out
    # appended, not overwritten
    main(["forward", "--n", "8", "--iterations", "3", "--out", str(out)])
    assert len(out.read_text().splitlines()) == 4


def test_forward_on_a_mesh_file(capsys):
    from conftest import MESH_DIR
    status = main(["forward", "--mesh", str(MESH_DIR / "square_quad.msh"), "--element", "Q1",
                   "--iterations", "200"])
    assert status == 0
    last = capsys.readouterr().out.strip().splitlines()[-2].split()
    assert float(last[3]) < 1e-10  # relative L2 error at K = 200


@pytest.mark.parametrize(("argv", "message"), [
    (["forward", "--mesh", "missing.msh"], "missing.msh: file does not exist"),
    (["forward", "--scene", "torus"], "scene 'torus': expected one of"),
    (["forward", "--iterations", "-3"], "expected integers >= 0"),
    (["forward", "--n", "4", "--element", "P7"], "element='P7'"),
    (["mesh", "nowhere.vtu"], "nowhere.vtu: file does not exist"),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("prdp-fem: error: ") and message in err


def test_mesh_report(capsys):
    from conftest import MESH_DIR
    assert main(["mesh", str(MESH_DIR / "plate_hole.msh")]) == 0
    out = capsys.readouterr().out
    assert "boundary: hole" in out
    assert "cell_type: triangle" in out


@pytest.mark.slow  # test_bench's bench cg test checks the same table, dofs and nnz included
def test_bench_cg_reports_the_operator(capsys):
    assert main(["bench", "cg", "--sides", "16", "--iterations", "5", "--repeats", "1"]) == 0
    row = capsys.readouterr().out.strip().splitlines()[-1].split()
    assert int(row[0]) == 15 * 15  # interior dofs of a 16 x 16 square
    assert int(row[1]) == 15 * 15 + 4 * 15 * 14  # five-point pattern of P1 on right triangles
    assert len(row) == 10  # dofs, nnz, SpMV, iteration, ratio, XLA iteration and ratio, COO
    # iteration and ratio, compile


def test_ctrl_c_inside_a_jax_host_callback_counts_as_an_interrupt():
    """The iteration counter taps run as host callbacks; a Ctrl-C landing in one reaches the
    CLI as a JaxRuntimeError naming KeyboardInterrupt, which must exit 130 like any Ctrl-C."""
    import jax

    from prdp_fem.cli._shared import is_interrupt
    wrapped = jax.errors.JaxRuntimeError(
        "INTERNAL: CpuCallback error calling callback: ... KeyboardInterrupt: ")
    assert is_interrupt(KeyboardInterrupt()) and is_interrupt(wrapped)
    assert not is_interrupt(jax.errors.JaxRuntimeError("INTERNAL: out of memory"))
    assert not is_interrupt(RuntimeError("KeyboardInterrupt"))


def test_bad_learned_table_is_one_line_and_exit_2(tmp_path, capsys):
    path = tmp_path / "learned.toml"
    path.write_text("[inverse]\nunknown = 'source'\n[learned]\nsamples = 8\nlayers = [4]\n")
    assert main(["study", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("prdp-fem: error: ")
    assert str(path) in err and "unknown key 'learned.layers'" in err and "hidden" in err
    assert main(["study", str(path).replace("learned", "x"), "--steps", "0"]) == 2
    path.write_text("[inverse]\nunknown = 'source'\n[learned]\nsamples = 8\n")
    assert main(["study", str(path), "--steps", "0"]) == 2
    assert "a learned study's epochs; expected an integer >= 1" in capsys.readouterr().err


@pytest.mark.parametrize("argv, code", [(["scenes"], 0), (["scenes", "no-such-scene"], 2)])
def test_the_program_exits_with_mains_code_and_a_frozen_heap(argv, code, monkeypatch, capsys):
    """``prdp-fem`` (run) leaves the heap to the exit frozen, so Python's last collections
    skip it; main, as called here in a live process, does not freeze anything."""
    assert gc.get_freeze_count() == 0
    assert main(argv) == code and gc.get_freeze_count() == 0
    monkeypatch.setattr(sys, "argv", ["prdp-fem", *argv])
    try:
        with pytest.raises(SystemExit) as exit:
            run()
        assert exit.value.code == code and gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()


def test_version_and_plain_help(capsys):
    import prdp_fem

    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"prdp-fem {prdp_fem.__version__}"
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "bench prdp" in text and "``" not in text and ":mod:" not in text


def test_the_program_switches_the_compilation_cache_on(tmp_path, monkeypatch, capsys):
    """The import leaves JAX's persistent cache alone; the program points it at the
    directory the environment names (checked in a fresh process: JAX's setting is global)."""
    import subprocess

    script = ("import jax, prdp_fem\n"
              "before = jax.config.jax_compilation_cache_dir\n"
              "from prdp_fem.cli.main import main\n"
              "main(['scenes'])\n"
              "print(repr(before), repr(jax.config.jax_compilation_cache_dir))\n")
    env = {**__import__("os").environ, "PRDP_FEM_COMPILATION_CACHE": str(tmp_path / "c")}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          env=env, timeout=120, check=True)
    assert done.stdout.strip().splitlines()[-1] == f"None {str(tmp_path / 'c')!r}"
