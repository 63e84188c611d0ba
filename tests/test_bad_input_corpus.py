"""A corpus of malformed inputs run through the ``prdp-fem`` command in-process: each exits 2
with exactly one line on stderr that names the file (or option) and the field at fault, and
no traceback. Each case is one check; removing the check turns its case into a traceback, a
different exit code or a message that no longer names the fault.
"""

import re
import struct

import pytest

import prdp_fem as pf
from prdp_fem.cli.main import main
from prdp_fem.scene.expressions import MAX_FORMULA_DEPTH, MAX_FORMULA_LENGTH

SQUARE_22 = """$MeshFormat
2.2 0 8
$EndMeshFormat
$Nodes
4
{a} 0 0 0
{b} X 0 0
{c} X X 0
{d} 0 X 0
$EndNodes
$Elements
2
1 2 2 0 1 {a} {b} {c}
2 2 2 0 1 {a} {c} {d}
$EndElements
"""

SQUARE_41 = """$MeshFormat
4.1 0 8
$EndMeshFormat
$Nodes
1 4 {a} {d}
2 1 0 4
{a}
{b}
{c}
{d}
0 0 0
1 0 0
1 1 0
0 1 0
$EndNodes
$Elements
1 2 1 2
2 1 2 2
1 {a} {b} {c}
2 {a} {c} {d}
$EndElements
"""

BIG_ID = 2_100_000_000


def square_22(ids=(1, 2, 3, 4), size="1"):
    a, b, c, d = ids
    return SQUARE_22.format(a=a, b=b, c=c, d=d).replace("X", size)


def square_41(ids=(1, 2, 3, 4)):
    a, b, c, d = ids
    return SQUARE_41.format(a=a, b=b, c=c, d=d)


def binary_41_with_a_huge_id(tmp_path) -> str:
    """The shipped binary Gmsh 4.1 cube with its first node block's last id set to 2.1e9."""
    from conftest import MESH_DIR

    data = bytearray((MESH_DIR / "cube_tet.msh").read_bytes())
    start = data.index(b"$Nodes\n") + len(b"$Nodes\n") + 4 * 8  # the section's 4 size_t
    count = struct.unpack_from("<Q", data, start + 12)[0]  # after dim, tag, parametric
    struct.pack_into("<Q", data, start + 20 + 8 * (count - 1), BIG_ID)
    (tmp_path / "huge41b.msh").write_bytes(bytes(data))
    return "huge41b.msh"


def _files(tmp_path) -> dict[str, object]:
    """The corpus's files, written to tmp_path: name -> content (str) or a writer."""
    return {
        "sparse22.msh": square_22((1, 2, BIG_ID, BIG_ID + 1)),
        "sparse41.msh": square_41((1, 2, BIG_ID, BIG_ID + 1)),
        "claims22.msh": square_22().replace("$Nodes\n4\n", "$Nodes\n2000000000\n"),
        "claims41.msh": square_41().replace("1 4 1 4\n", "1 2000000000 1 4\n"),
        "far.msh": square_22(size="1e300"),
        "longf.toml": f'[pde]\nkappa = "{"+".join(["x"] * 200_000)}"\n',
        "deepf.toml": f'[pde]\nsource = "{"+" * 100_000}x"\n',
        "deep2.toml": f'[pde]\nsource = "{"+".join(["x"] * (MAX_FORMULA_DEPTH + 2))}"\n',
        "bign.toml": "[mesh]\nn = 1000000000\n",
        "bigrefine.toml": "[mesh]\nrefine = 40\n",
        "bigcube.toml": '[mesh]\ngenerator = "unit_cube"\nn = 300\n',
        "filerefine.toml": '[mesh]\nfile = "ok.msh"\nrefine = 40\n',
        "levels.toml": '[pde]\nexact = "x"\n[study]\nkind = "h"\nlevels = [4, 100000]\n',
        "ok.msh": square_22(),
    }


CASES = [
    # command line, what the one line must contain
    (["mesh-info", "sparse22.msh"], r"sparse22\.msh: node ids run up to 2100000001 for 4 "
     r"nodes.*expected node ids at most 10000000"),
    (["solve", "sparse22.msh"], r"sparse22\.msh: node ids run up to 2100000001"),
    (["mesh-info", "sparse41.msh"], r"sparse41\.msh: node ids run up to 2100000001 for 4 "),
    (["mesh-info", "huge41b.msh"], rf"huge41b\.msh: node ids run up to {BIG_ID} for 341 "),
    (["mesh-info", "claims22.msh"], r"claims22\.msh: .*\$Nodes declares 2000000000 nodes but "
     r"the file holds \d+ bytes"),
    (["mesh-info", "claims41.msh"], r"claims41\.msh: .*\$Nodes declares 2000000000 nodes in "
     r"1 blocks but the file holds"),
    (["mesh-info", "far.msh"], r"far\.msh: 3 node\(s\) have coordinates beyond \+-1e\+50 .*"
     r"would overflow"),
    (["solve", "longf.toml"], rf"longf\.toml: pde\.kappa = 'x\+x.*: 399999 characters; "
     rf"expected a formula of at most {MAX_FORMULA_LENGTH} characters"),
    (["solve", "deepf.toml"], r"deepf\.toml: pde\.source = .*100001 characters"),
    (["solve", "deep2.toml"], rf"deep2\.toml: pde\.source = .*nested more than "
     rf"{MAX_FORMULA_DEPTH} levels deep"),
    (["solve", "bign.toml"], r"bign\.toml: mesh\.n = 1000000000: unit_square\(n=1000000000\) "
     r"would carry about 1e\+18 degrees of freedom; expected at most 20000000"),
    (["study", "bigrefine.toml"], r"bigrefine\.toml: mesh\.refine = 40: .* refined 40 times"),
    (["solve", "bigcube.toml"], r"bigcube\.toml: mesh\.n = 300: unit_cube\(n=300\) would "
     r"carry about 2\.73e\+07"),
    (["solve", "--max-dofs", "100", "bigcube.toml"], r"mesh\.n = 300: .*expected at most 100 "),
    (["solve", "filerefine.toml"], r"filerefine\.toml: mesh\.refine = 40: even one cell"),
    (["study", "levels.toml"], r"levels\.toml: study\.levels = 100000: unit_square"),
    (["solve", "ok.msh", "--max-dofs", "0"], r"--max-dofs 0: expected an integer >= 1"),
    (["solve", "loop.msh"], r"loop\.msh: is a symbolic link loop \(.*\); expected a mesh file"),
    (["mesh-info", "loop.msh"], r"loop\.msh: is a symbolic link loop"),
    (["solve", "loop.toml"], r"loop\.toml: is a symbolic link loop"),
    (["mesh-info", "dangling.msh"], r"dangling\.msh: is a symbolic link to 'gone\.msh', "
     "which does not exist"),
]


@pytest.fixture
def corpus(tmp_path, monkeypatch):
    for name, content in _files(tmp_path).items():
        (tmp_path / name).write_text(content)
    binary_41_with_a_huge_id(tmp_path)
    for name in ("loop.msh", "loop.toml"):
        (tmp_path / name).symlink_to(name)
    (tmp_path / "dangling.msh").symlink_to("gone.msh")
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("PRDP_FEM_MAX_DOFS", raising=False)
    return tmp_path


@pytest.mark.parametrize(("argv", "message"), CASES, ids=[" ".join(c[0]) for c in CASES])
def test_bad_input_exits_2_with_one_line(corpus, capsys, argv, message):
    before = sorted(p.name for p in corpus.iterdir())
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("prdp-fem: error: ")
    assert re.search(message, err), err
    assert sorted(p.name for p in corpus.iterdir()) == before  # nothing written


def test_the_reference_files_load(corpus):
    """The corpus's files are malformed only where meant: the same meshes with ids 1..4 load,
    and ids with gaps below the limit load too."""
    assert pf.load_mesh(corpus / "ok.msh").p.shape == (2, 4)
    (corpus / "gaps.msh").write_text(square_41((1, 2, 9_000_000, 9_000_001)))
    assert pf.load_mesh(corpus / "gaps.msh").t.shape == (3, 2)
