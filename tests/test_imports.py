"""Importing the package loads only what every scene needs: pyamg and meshio come with the
first AMG hierarchy and the first mesh file (0.07-0.09 s and 0.04-0.06 s of each import)."""

import json
import subprocess
import sys

from conftest import MESH_DIR

_CHILD = """
import json, sys
import numpy as np
import prdp_fem as pf
# what `prdp-fem study` imports before a scene's needs
import prdp_fem.cli.main, prdp_fem.studies.runner
from prdp_fem.bench.inverse import solve_mother

def loaded():
    return sorted(name for name in ("pyamg", "meshio") if name in sys.modules)

figures = {"import": loaded()}
figures["error"] = solve_mother(8, target=0.5, solver="reduced").error
figures["jacobi inversion"] = loaded()
disc = pf.discretize(pf.load_mesh(sys.argv[1]), element="P1", dirichlet=0.0)
figures["mesh file"] = loaded()
operator = disc.system.operator(np.ones(disc.n_kappa))
figures["levels"] = len(pf.amg_preconditioner(operator).levels)
figures["amg"] = loaded()
print(json.dumps(figures))
"""


def test_pyamg_and_meshio_load_with_the_first_hierarchy_and_mesh_file():
    done = subprocess.run([sys.executable, "-c", _CHILD, str(MESH_DIR / "square_tri.msh")],
                          capture_output=True, text=True, timeout=300, check=True)
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    assert figures["import"] == figures["jacobi inversion"] == []
    assert 0 < figures["error"] <= 0.5
    assert figures["mesh file"] == ["meshio"]
    assert figures["levels"] >= 1 and figures["amg"] == ["meshio", "pyamg"]
