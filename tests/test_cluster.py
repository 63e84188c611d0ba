"""Studies on a Dask cluster (``run_study(..., client=...)``, ``prdp-fem study --executor``):
the same records as a serial study, written by the study's process alone, and a worker
killed mid-study loses no record and writes none twice."""

import json
import os
import signal
import sys
import threading
import time

import pytest

from prdp_fem.cli.main import main
from prdp_fem.scene import load_scene
from prdp_fem.scene.spec import with_overrides
from prdp_fem.studies import run_study
from prdp_fem.studies.cluster import ClusterError, cluster_client, parse_executor
from prdp_fem.studies.runner import RESULTS

# the columns that depend on the machine's speed, not on what was computed
TIMED = {"time", "compile_time"}


def _scene(steps: int = 6):
    return with_overrides(load_scene("inclusion"), {"optimizer": {"steps": steps}})


def _records(out):
    return [json.loads(line) for line in (out / RESULTS).read_text().splitlines()]


def _by_run(records):
    """Each run's step records without their timings, in step order, and its done records."""
    runs = {}
    for record in records:
        if record["type"] == "step":
            runs.setdefault(record["run"], []).append(
                {k: v for k, v in record.items() if k not in TIMED})
    done = [(r["run"], r["attempt"]) for r in records if r["type"] == "done"]
    return runs, done


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "study"
    result = run_study(_scene(), out)
    return out, result


@pytest.mark.slow  # a LocalCluster's start and a study on it: 45 s of the default suite's CPU
def test_a_cluster_study_writes_the_serial_studys_records_and_resumes(serial, tmp_path):
    serial_out, serial_result = serial
    out = tmp_path / "study"
    with cluster_client(None, n_workers=2) as client:
        result = run_study(_scene(), out, client=client)
        runs, done = _by_run(_records(out))
        expected_runs, expected_done = _by_run(_records(serial_out))
        assert runs == expected_runs  # every step's losses, errors and iterations, exactly
        assert sorted(done) == sorted(expected_done) and len(done) == len(set(done))
        assert sorted(result.ran) == sorted(serial_result.ran)
        # the fields the workers wrote came back into the study directory, byte for byte
        fields = sorted(p.name for p in (out / "fields").iterdir())
        assert fields == sorted(p.name for p in (serial_out / "fields").iterdir())
        for name in fields:
            assert (out / "fields" / name).read_bytes() == \
                (serial_out / "fields" / name).read_bytes()
        columns = ("run", "final_error", "cg_iterations", "reached_step", "iteration_saving")
        assert [{k: row[k] for k in columns} for row in result.summary] == \
            [{k: row[k] for k in columns} for row in serial_result.summary]

        # resumed with one configuration finished: only the others run, each once
        resumed = tmp_path / "resumed"
        resumed.mkdir()
        records = _records(serial_out)
        first = records[0]["run"]
        kept = [r for r in records if r.get("run") == first]
        (resumed / RESULTS).write_text("".join(json.dumps(r) + "\n" for r in kept))
        (resumed / "study.json").write_text((serial_out / "study.json").read_text())
        result = run_study(_scene(), resumed, resume=True, client=client)
    assert first not in result.ran and len(result.ran) == len(_scene().runs()) - 1
    runs, done = _by_run(_records(resumed))
    assert runs == expected_runs
    assert len(done) == len(set(done)) == len(_scene().runs())


@pytest.mark.slow(reason="a 2-worker Dask cluster and two studies: 20 s")
def test_a_worker_killed_mid_study_loses_no_record_and_writes_none_twice(serial, tmp_path):
    serial_out, _ = serial
    out = tmp_path / "study"
    outcome = {}
    with cluster_client(None, n_workers=2) as client:

        def study():
            try:
                outcome["result"] = run_study(_scene(), out, client=client)
            except BaseException as error:  # re-raised in the test's thread below
                outcome["error"] = error

        thread = threading.Thread(target=study)
        thread.start()
        victim = None
        deadline = time.monotonic() + 120
        while victim is None and time.monotonic() < deadline and thread.is_alive():
            busy = [worker for worker, keys in client.processing().items() if keys]
            if busy:
                time.sleep(0.5)  # well into the task (its compile alone takes longer)
                if client.processing().get(busy[0]):  # still running one: kill it there
                    victim = busy[0]
            else:
                time.sleep(0.05)
        assert victim is not None, "no task was seen running"
        pid = client.run(os.getpid, workers=[victim])[victim]
        os.kill(pid, signal.SIGKILL)
        thread.join(timeout=300)
        assert not thread.is_alive()
    if "error" in outcome:
        raise outcome["error"]
    runs, done = _by_run(_records(out))
    assert runs == _by_run(_records(serial_out))[0]
    assert sorted(done) == sorted((name, 1) for name, _ in _scene().runs())


def test_executor_specs():
    assert parse_executor("serial") == ("serial", None)
    assert parse_executor("dask") == ("dask", None)
    assert parse_executor("dask=tcp://127.0.0.1:8786") == ("dask", "tcp://127.0.0.1:8786")
    for bad in ("threads", "dask=", "serial=x", ""):
        with pytest.raises(ClusterError, match="expected 'serial', 'dask'"):
            parse_executor(bad)


def test_a_bad_executor_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["study", "inclusion", "--out", str(tmp_path / "s"), "--executor",
                 "threads"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--executor 'threads'" in err[0]
    assert not (tmp_path / "s").exists()


def test_without_dask_the_executor_says_how_to_install_it(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed fails
    assert main(["study", "inclusion", "--out", str(tmp_path / "s"), "--executor",
                 "dask"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install -e '.[cluster]'" in err[0]
    assert not (tmp_path / "s").exists()


def test_an_unreachable_scheduler_is_a_cluster_error():
    with pytest.raises(ClusterError, match="no scheduler reached"), \
            cluster_client("tcp://127.0.0.1:9", timeout="1s"):
        pass


def test_bench_prdp_checks_its_executor_first(tmp_path, capsys, monkeypatch):
    assert main(["bench", "prdp", "--scene", "plate_hole", "--out", str(tmp_path / "b"),
                 "--executor", "threads"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--executor 'threads'" in err[0]
    assert not (tmp_path / "b").exists()
    monkeypatch.setitem(sys.modules, "distributed", None)
    assert main(["bench", "prdp", "--scene", "plate_hole", "--out", str(tmp_path / "c"),
                 "--executor", "dask"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install -e '.[cluster]'" in err[0]
    assert not (tmp_path / "c").exists()


@pytest.mark.slow(reason="a local Dask cluster and two benchmark runs: 30 s")
def test_bench_prdp_on_a_cluster_counts_what_the_serial_run_counts(tmp_path):
    def saving(out, *executor):
        assert main(["bench", "prdp", "--scene", "plate_hole", "--steps", "8", "--out",
                     str(out), *executor]) == 0
        rows = (out / "saving.csv").read_text().splitlines()
        header = rows[0].split(",")
        counted = [header.index(c) for c in ("run", "converged_iterations",
                                             "prdp_iterations", "reached_step")]
        return [[row.split(",")[i] for i in counted] for row in rows[1:]]

    assert saving(tmp_path / "cluster", "--executor", "dask") == saving(tmp_path / "serial")


@pytest.mark.slow(reason="a one-worker Dask cluster and a study: 20 s")
def test_the_command_runs_a_study_on_a_running_scheduler(serial, tmp_path, capsys):
    """``--executor dask=ADDRESS``: the scheduler of a cluster started apart, as a user's."""
    import distributed

    serial_out, _ = serial
    out = tmp_path / "study"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        assert main(["study", "inclusion", "--steps", "6", "--out", str(out), "--executor",
                     f"dask={cluster.scheduler_address}"]) == 0
    assert "PRDP (prdp)" in capsys.readouterr().out
    assert _by_run(_records(out))[0] == _by_run(_records(serial_out))[0]
