"""The seed paper's claims at the CI size (benchmarks/validation/seed_paper.py; VALIDATION.md section 4)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "validation" / "seed_paper.py"


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    spec = importlib.util.spec_from_file_location("seed_paper", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.main(["--quick", "--out", str(tmp_path_factory.mktemp("seed") / "seed.json")])


def test_force_and_moment_are_the_gradients_of_the_volume(result):
    cases = list(result["fig1"].values())
    assert max(max(c["force_fd_error"]) for c in cases) < 1e-6
    assert max(max(c["moment_fd_error"]) for c in cases) < 1e-6
    assert result["random"]["force_fd_error"] < 1e-6 and result["random"]["moment_fd_error"] < 1e-6


def test_facet_forces_are_in_equilibrium_and_the_contact_point_is_on_the_axis(result):
    for c in [*result["fig1"].values(), {k: [v] for k, v in result["random"].items() if k != "poses"}]:
        assert max(c["equilibrium_force"]) < 1e-10
        assert max(c["equilibrium_moment"]) < 1e-10
        assert max(c["contact_point_off_axis"]) < 1e-10
        assert max(c["contact_point_off_plane"]) < 1e-10
    # Fig. 1, symmetric: the normal lies along the line of the two corners.
    np.testing.assert_allclose(result["fig1_symmetric_normal"], [1.0, 0.0, 0.0], atol=1e-9)


def test_the_normal_turns_continuously_where_a_separating_axis_jumps(result):
    rows = result["smoothness"]
    turns = [r["energy_normal_max_turn_deg"] for r in rows]
    for coarse, fine in zip(turns, turns[1:], strict=False):
        assert fine < 0.6 * coarse  # halves with the spacing: no jump
    assert all(r["sat_normal_max_turn_deg"] > 10.0 for r in rows)  # the feature-based normal jumps
    assert rows[-1]["energy_normal_total_turn_deg"] == pytest.approx(rows[-1]["sat_normal_max_turn_deg"], rel=1e-3)


def test_an_undamped_impact_gives_back_its_energy(result):
    for r in result["impact_energy"]:
        assert r["met"]
        assert abs(r["relative_change"]) < 1e-6, r
