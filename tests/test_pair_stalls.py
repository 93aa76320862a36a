"""benchmarks/pair_stalls.py's parts that run without Nsight Compute: the case names, the reading of ncu's CSV
pages, and the pour its pileN case profiles (ncu itself runs only on the GPU machine)."""

import argparse

import pytest
from benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def stalls():
    return load_benchmark("pair_stalls", "pair_stalls_benchmark")


def test_case_names(stalls):
    assert stalls.case_kind("one") == ("one", 1)
    assert stalls.case_kind("spread1024") == ("spread", 1024)
    assert stalls.case_kind("packed64") == ("packed", 64)
    assert stalls.case_kind("pile1000") == ("pile", 1000)
    with pytest.raises(SystemExit, match="unknown case 'spread'"):
        stalls.case_kind("spread")


def test_stall_shares_prefer_the_sampled_counts(stalls):
    # ncu's raw page: a row of units, then the kernel's row; the sampled counts win over WarpStateStats' ratios,
    # a reason's "not issued" part is not a reason of its own
    units = {"smsp__pcsamp_warps_issue_stalled_long_scoreboard": "(count)"}
    row = {
        "ID": "0",
        "smsp__pcsamp_warps_issue_stalled_long_scoreboard": "1,200",
        "smsp__pcsamp_warps_issue_stalled_long_scoreboard_not_issued": "900",
        "smsp__pcsamp_warps_issue_stalled_wait": "300",
        "smsp__average_warps_issue_stalled_branch_resolving_per_issue_active.ratio": "7.5",
    }
    assert stalls.stall_shares([units, row]) == {"long_scoreboard": 0.8, "wait": 0.2}
    ratios = {
        "smsp__average_warps_issue_stalled_long_scoreboard_per_issue_active.ratio": "3.0",
        "smsp__average_warps_issue_stalled_wait_per_issue_active.ratio": "1.0",
    }
    assert stalls.stall_shares([ratios]) == {"long_scoreboard": 0.75, "wait": 0.25}
    assert stalls.stall_shares([{"ID": "0"}]) == {}


def test_top_lines_by_samples(stalls):
    rows = [
        {"#": "10", "Source": "a = b", "Warp Stall Sampling (All Samples)": "10"},
        {"#": "11", "Source": "  c = shapes.face_plane[f]", "Warp Stall Sampling (All Samples)": "30"},
        {"#": "12", "Source": "d", "Warp Stall Sampling (All Samples)": "0"},
    ]
    top = stalls.top_lines(rows, 5)
    assert [(t["at"], t["source"], t["share"]) for t in top] == [("11", "c = shapes.face_plane[f]", 0.75),
                                                                 ("10", "a = b", 0.25)]  # fmt: skip
    assert stalls.top_lines([{"#": "1", "Source": "x"}], 5) == []


def test_the_pile_case_runs_the_pour(stalls, device):
    """The pour the pileN case profiles under ncu (time_to_settle.py's, without graphs) builds and steps."""
    args = argparse.Namespace(device=device, pile_shapes="cube", pile_steps=2)
    stalls.pile_child(args, 200)


DISASSEMBLY = """\
//--------------------- .text.k_forward --------------------------
.text.k_forward:
\t//## File "/x/tile.h", line 9 inlined at "/x/kernels/narrowphase.py", line 138
        /*0000*/                   LDC R1, c[0x0][0x28] ;
\t//## File "/x/builtin.h", line 5 inlined at "/x/kernels/geometry.py", line 3
\t//## File "/x/kernels/geometry.py", line 3 inlined at "/x/kernels/geometry.py", line 7
\t//## File "/x/kernels/geometry.py", line 7 inlined at "/x/kernels/narrowphase.py", line 140
        /*0010*/                   FMUL R2, R3, R4 ;
        /*0020*/              @P2  BRA 0x40 ;
\t//## File "/x/kernels/geometry.py", line 8 inlined at "/x/kernels/narrowphase.py", line 140
        /*0030*/                   DADD R6, R6, R8 ;
"""

GEOMETRY = "def helper(x):\n    y = 1\n    return y\n\ndef outer(z):\n    pass\n    a = helper(z)\n    b = 2\n"

PAGE = """\
"Kernel Name","k_forward",
"Address","Source","Warp Stall Sampling (All Samples)","Instructions Executed"
"0x7f00","LDC R1, c[0x0][0x28]","10","1"
"0x7f10","FMUL R2, R3, R4","30","4"
"0x7f20","@P2   BRA 0x7f40","20","4"
"0x7f30","DADD R6, R6, R8","40","1"
"""


def test_sass_lines_attributes_samples_to_the_innermost_python_line(tmp_path):
    """sass_lines.py (pair_stalls' Python lines): each SASS instruction of ncu's page counted at the innermost
    Python line of nvdisasm -gi's inlining chain (an instruction without a chain takes the one above it), and at
    the def around that line; opcodes compared without predicates."""
    lines = load_benchmark("sass_lines")
    kernels = tmp_path / "kernels"
    kernels.mkdir()
    (kernels / "geometry.py").write_text(GEOMETRY)
    kernel, rows = lines.read_page(PAGE)
    assert kernel == "k_forward" and len(rows) == 4
    functions = lines.read_disassembly(DISASSEMBLY)
    assert list(functions) == ["k_forward"]
    name, by_line, by_def, differ = lines.attribute(functions, kernel, rows, "inner", [str(kernels)])
    assert name == "k_forward" and differ == 0
    nar, geo = "/x/kernels/narrowphase.py", "/x/kernels/geometry.py"
    assert dict(by_line) == {(nar, 138): [10.0, 1.0], (geo, 3): [50.0, 8.0], (geo, 8): [40.0, 1.0]}
    assert dict(by_def) == {("narrowphase.py", "?"): [10.0, 1.0], ("geometry.py", "helper"): [50.0, 8.0],
                            ("geometry.py", "outer"): [40.0, 1.0]}  # fmt: skip
    _, outer, _, _ = lines.attribute(functions, kernel, rows, "outer", [str(kernels)])
    assert dict(outer) == {(nar, 138): [10.0, 1.0], (nar, 140): [90.0, 9.0]}
    top = lines.table(by_line, 2)
    assert [t["at"][1] for t in top] == [3, 8] and top[0]["samples"] == 0.5
    # another cubin's page: its opcodes differ, and the script says so
    _, _, _, differ = lines.attribute(functions, kernel, [dict(r, Source="IADD R1") for r in rows])
    assert differ == 4
