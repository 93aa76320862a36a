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
