"""``prdp-fem bench scale`` (prdp_fem.bench.scale) on sizes a test can afford: the rows
hold together (savings from the times to target, dofs from the mesh); the big figures are
the benchmark's, in docs/benchmarks.md."""

import math

import pytest

from prdp_fem.bench.scale import inversion_at_scale, parse_mesh, sharded_iteration
from prdp_fem.cli.main import main
from prdp_fem.errors import SolverConfigError


def test_mesh_specs_parse_or_are_refused(capsys):
    assert parse_mesh("square:501") == ("square", 501)
    assert parse_mesh("cube:81") == ("cube", 81)
    for bad in ("square", "disk:10", "cube:2", "square:1e3"):
        with pytest.raises(SolverConfigError, match="expected square:N or cube:N"):
            parse_mesh(bad)
    assert main(["bench", "scale", "--meshes", "square:501", "cube:x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mesh 'cube:x'" in err[0]


@pytest.mark.slow  # a fresh process per mesh, two inversions each
def test_inversion_rows_measure_the_same_target_saving():
    rows = inversion_at_scale(["square:17", "cube:6"], steps=12)
    assert [(r.mesh, r.dofs) for r in rows] == [("square:17", 16 ** 2), ("cube:6", 5 ** 3)]
    for r in rows:
        assert r.steps == 12 and r.parameters > r.dofs  # P1 kappa on the boundary too
        assert 0 <= r.converged_reached_step <= 12
        assert math.isclose(r.time_saving, 1 - r.prdp_to_target_s / r.converged_to_target_s)
        assert math.isclose(r.at_or_below_saving,
                            1 - r.prdp_at_or_below_s / r.converged_to_target_s)
        assert r.prdp_at_or_below_s <= r.prdp_to_target_s  # inside the band is at or below
        assert r.converged_step_s > 0 and r.prdp_step_s > 0 and 0 < r.peak_rss_gb < 8
        assert abs(r.prdp_error - r.converged_error) <= 0.01 * r.converged_error


@pytest.mark.slow  # a process with 4 forced host devices
def test_sharded_iteration_rows_per_device_count():
    rows = sharded_iteration(17, devices=(1, 4), iterations=5, repeats=2)
    assert [(r.devices, r.dofs) for r in rows] == [(0, 256), (1, 256), (4, 256)]
    assert rows[0].ratio == 1.0 and rows[0].halo == rows[1].halo == 0
    # four blocks of a 16 x 16 grid: the inner ones read one grid line from each side
    assert 16 <= rows[2].halo <= 2 * 17
    assert all(r.iteration_ms > 0 for r in rows)
