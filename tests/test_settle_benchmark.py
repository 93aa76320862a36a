"""benchmarks/settle.py's pile under another law (``--law power --exponent m``): the k of each rule and the step
that follows it (BENCHMARKS.md section 26)."""

import math

import pytest
from benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def settle():
    return load_benchmark("settle")


def design_face(opts, g=9.81):
    """The volume rule's face contact: its load [N] and overlap volume [m^3]."""
    load = opts.load_factor * opts.layers * opts.density * opts.edge**3 * g
    return load, opts.overlap * opts.edge**3


@pytest.mark.parametrize(("law", "m"), [("hertz", None), ("power", 2.0), ("power", 3.0)])
def test_the_volume_rule_presses_a_face_as_deep_under_every_law(settle, law, m):
    opts = settle.scene_options(k_rule="volume", law=law, exponent=m if m else 2.0)
    scene, info = settle.make_scene(20, opts)
    mat = scene.materials["grain"]
    assert (mat.law, info["law"], info["m"]) == (law, law, m)
    if law == "power":
        assert mat.m == m
    load, volume = design_face(opts)
    # W'(V) |S| with |S| the face, edge^2: hertz k sqrt(V), power k V^(m - 1)
    slope = math.sqrt(volume) if law == "hertz" else volume ** (m - 1.0)
    assert info["k_hertz"] * slope * opts.edge**2 == pytest.approx(load, rel=1e-12)


def test_the_power_law_step_follows_k_to_the_minus_half(settle):
    """A face under W = k V^2 / 2 is a linear spring: the recommended step halves for 4x k, where under hertz the
    resting rule quarters it."""
    steps = {}
    for law in ("hertz", "power"):
        for factor in (16.0, 64.0):
            opts = settle.scene_options(k_rule="volume", law=law, k_factor=factor)
            steps[law, factor] = settle.make_scene(20, opts)[0].time_step().recommended
    assert steps["power", 16.0] / steps["power", 64.0] == pytest.approx(2.0, rel=1e-9)
    assert steps["hertz", 16.0] / steps["hertz", 64.0] == pytest.approx(4.0, rel=1e-9)
