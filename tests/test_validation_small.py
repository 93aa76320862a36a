"""The validation scripts of VALIDATION.md at their smallest sizes (issue 26: "small versions run in CI"): they
check the machinery and the balances any size must hold, not the published numbers (those need the full sizes on a
GPU). Each runs the script as a user would, on every device present."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

VALIDATION = Path(__file__).resolve().parents[1] / "benchmarks" / "validation"


def run_script(name: str, *args: str) -> str:
    done = subprocess.run([sys.executable, str(VALIDATION / name), *args], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, f"{name} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout


def test_tapping_stops_resumes_and_its_checkpoint_reads_back(device, tmp_path):
    """120 cubes poured and tapped twice, stopped after the first record and resumed: every record there, each
    measure in its range over a measuring box of a few dozen grains; tap_order.py reads the checkpoint the stop
    left and finds the same packing."""
    common = ["--device", device, "--grains", "120", "--width", "6", "--margin", "1", "--taps", "2", "--start",
              "0.5", "--period", "0.2", "--coordination"]  # fmt: skip
    out = tmp_path / "tap.json"
    first = run_script("tapping.py", *common, "--stop-after", "0", "--out", str(out))
    assert "stopped, resume with --resume" in first
    stopped = json.loads(out.read_text())
    assert stopped["stopped"] and [r["tap"] for r in stopped["records"]] == [0]
    checkpoint = tmp_path / "tap.npz"
    saved = tmp_path / "tap_at_0.npz"
    saved.write_bytes(checkpoint.read_bytes())
    (tmp_path / "tap_at_0.json").write_text(out.read_text())
    run_script("tapping.py", *common, "--resume", str(checkpoint), "--out", str(out))
    records = json.loads(out.read_text())["records"]
    assert [r["tap"] for r in records] == [0, 1, 2]
    assert records[0] == stopped["records"][0]  # the records before the stop are kept as they were
    for r in records:
        assert r["grains_in_box"] >= 15
        assert 0.45 < r["packing_fraction"] < 0.75
        assert -2 / 3 <= r["cubic_order"] <= r["cubic_order_best"] <= 1.0 + 1e-12
        assert r["coordination"] >= 3.0
        assert sum(r["coordination_by_kind"].values()) == pytest.approx(r["coordination"], rel=1e-12)
    row = json.loads(run_script_json("tap_order.py", str(saved), "--device", device, out=tmp_path / "order.json"))
    assert row["packing_fraction"] == pytest.approx(records[0]["packing_fraction"], abs=2e-3)
    assert row["cubic_order"] == pytest.approx(records[0]["cubic_order"], abs=2e-3)
    assert row["grains_in_box"] == records[0]["grains_in_box"]
    assert row["coordination"] == pytest.approx(records[0]["coordination"], abs=0.5)


def run_script_json(name: str, *args: str, out: Path) -> str:
    run_script(name, *args, "--out", str(out))
    row = json.loads(out.read_text())["rows"][0]
    return json.dumps({**row, **row["coordination_by_kind"]})


def test_janssen_silo_balances_the_weight(device, tmp_path):
    """60 cubes filled in two batches into a silo 4 grains wide, the floor lowered 0.2 d: the floor and the side
    walls carry the grains' weight between them (the force balance of grains near rest, 5%), lowering the floor
    takes load off it, and the stress profile has a value for every slab."""
    out = tmp_path / "janssen.json"
    run_script("janssen.py", "--device", device, "--size", "tiny", "--stages", "2", "--fill-time", "0.45",
               "--max-time", "0.3", "--lower", "0.2", "--out", str(out))  # fmt: skip
    r = json.loads(out.read_text())
    assert r["grains"] == 60 and r["stages"] == 2
    for loads in (r, r["before_lowering"]):
        carried = loads["floor_apparent_mass"] + loads["side_walls_apparent_mass"]
        assert carried == pytest.approx(r["grain_mass"], rel=0.05)
    assert r["floor_apparent_mass"] < r["before_lowering"]["floor_apparent_mass"]
    assert 0.4 < r["packing_fraction"] < 0.75
    assert len(r["depth"]) == len(r["sigma_zz"]) == len(r["hydrostatic_sigma_zz"]) >= 2
    assert np.all(np.isfinite(r["sigma_zz"]))


def test_beverloo_smoke_run_discharges(device, tmp_path):
    """The tiny bins of 6 and 7 d: the fill comes to rest or its cap, grains leave through the orifice, and each
    run has a rate or says why it has none."""
    out = tmp_path / "beverloo.json"
    run_script("beverloo.py", "--device", device, "--size", "tiny", "--out", str(out))
    runs = json.loads(out.read_text())["runs"]
    assert sorted(round(r["D_over_d"]) for r in runs) == [6, 7]
    for r in runs:
        assert 0.4 < r["packing_fraction"] < 0.8
        assert r["discharged"][-1] > 0
        assert r["rate"] is not None or r["why_no_rate"]
        if r["rate"] is not None:
            assert r["rate"]["slope"] > 0.0


def test_validation_figures_are_drawn_from_the_results(tmp_path):
    """plots.py draws VALIDATION.md's four figures from the committed result files."""
    pytest.importorskip("matplotlib")
    done = subprocess.run([sys.executable, str(VALIDATION / "plots.py"), "--out", str(tmp_path)], capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    for name in ("taps", "anneal", "janssen", "beverloo"):
        png = tmp_path / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
