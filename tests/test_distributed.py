"""Decomposed runs (polydem.distributed): slabs, and the same result on 1, 2 and 4 ranks as undivided.

The MPI cases launch ``mpiexec -n R python tests/mpi_job.py ...`` (mpi4py and the MPICH wheel come
with the test extra) and compare the gathered state and contact list with a Simulation of the same
scene, bit for bit.
"""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from distributed_scenes import build
from polydem.kernels.response import DAMPING_SHARE

from polydem import Simulation
from polydem.distributed import DistributedSimulation, launched_size
from polydem.distributed import partition as part
from polydem.distributed.comm import SerialComm
from polydem.run_settings import run_settings

HERE = Path(__file__).resolve().parent


def test_cuts_balance_the_bodies():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(0.0, 1.0, 30000), rng.uniform(3.0, 4.0, 10000)])  # a lopsided pile
    counts = np.histogram(x, bins=part.HISTOGRAM_BINS, range=(x.min(), x.max()))[0]
    for ranks in (1, 2, 3, 8):
        cuts = part.cuts_from_histogram(counts, x.min(), x.max(), ranks)
        owned = np.bincount(part.owner(x, cuts), minlength=ranks)
        assert owned.sum() == len(x) and len(owned) == ranks
        # Cuts fall on bin edges: each slab is off by at most the largest bin's count.
        assert np.all(np.abs(owned - len(x) / ranks) <= counts.max() + 1), owned


def test_holders_cover_the_interaction_range():
    cuts = np.array([-np.inf, 0.0, 1.0, np.inf])
    x = np.array([-0.5, -0.05, 0.02, 0.5, 0.97, 1.2])
    held = part.holders(x, cuts, 0.1)
    np.testing.assert_array_equal(part.owner(x, cuts), [0, 0, 1, 1, 1, 2])
    np.testing.assert_array_equal(
        held,
        [[1, 0, 0], [1, 1, 0], [1, 1, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1]],
    )


def test_one_rank_is_the_simulation(device):
    scene = build("box_pour")
    ds = DistributedSimulation(scene, device=device, comm=SerialComm())
    sim = Simulation(build("box_pour"), device=device)
    # Step calls of several lengths: the time must round as Simulation's sum over its own chunks does (a
    # checkpoint and the frame times of a decomposed run are the undivided run's), not as steps * dt.
    for n in (1, 2, 63, 64, 65, 105):
        ds.step(n)
        sim.step(n)
        assert ds.steps_done == sim.steps_done and ds.time == sim.time, (n, ds.time.hex(), sim.time.hex())
    a, b = ds.state(), sim.state()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert ds.partitions >= 1 and launched_size() == 1


def test_a_simulation_of_some_bodies_takes_the_whole_scenes_settings(device):
    """A rank's Simulation: the bodies given, sliced out of the scene, with the settings of the whole scene's
    run, although these bodies alone (the larger tetrahedra and the box) would give others."""
    scene = build("box_pour")
    settings = run_settings(scene)
    whole = Simulation(scene, device=device, settings=settings)
    kind = np.asarray(scene.body_kind)
    big = np.asarray(scene.body_shape) == scene.shape_index("big")
    index = np.flatnonzero(big | (kind != 0))
    part = Simulation(scene, device=device, validate=False, settings=settings, bodies=index)
    # The cubes set the skin and the size classes: smaller than any free body of the part.
    radius = part.model.body_radius.numpy()
    assert settings.radius_ref < radius[kind[index] == 0].min()
    assert part.dt == whole.dt and part.skin == whole.skin == settings.skin
    assert part.current_contacts.broadphase.radius_ref == settings.radius_ref
    m, w = part.model, whole.model
    np.testing.assert_array_equal(m.body_index, index)
    np.testing.assert_array_equal(m.material_kt.numpy(), w.material_kt.numpy())
    np.testing.assert_array_equal(m.body_mass.astype(np.float64), scene.body_mass()[index])
    np.testing.assert_array_equal(m.body_inertia.numpy(), w.body_inertia.numpy()[index])
    np.testing.assert_array_equal(m.body_inv_mass.numpy(), w.body_inv_mass.numpy()[index])
    np.testing.assert_array_equal(m.body_radius.numpy(), w.body_radius.numpy()[index])
    for k, v in part.state().items():
        np.testing.assert_array_equal(v, whole.state()[k][index], err_msg=k)
    with pytest.raises(ValueError, match="run_settings"):
        Simulation(scene, device=device, settings=settings, skin=1e-3)


def _mpiexec():
    here = Path(sys.executable).parent / "mpiexec"
    return str(here) if here.exists() else shutil.which("mpiexec")


def _have_mpi():
    try:
        import mpi4py  # noqa: F401
    except ImportError:
        return False
    return _mpiexec() is not None


needs_mpi = pytest.mark.skipif(not _have_mpi(), reason="needs mpi4py and mpiexec (pip install '.[test]')")


def test_the_nccl_exchange_asks_for_a_gpu_and_a_known_name():
    scene = build("box_pour")
    with pytest.raises(ValueError, match="exchange must be one of"):
        DistributedSimulation(scene, device="cpu", comm=SerialComm(), exchange="mpi")
    with pytest.raises(ValueError, match="between GPUs, but this rank runs on cpu"):
        DistributedSimulation(scene, device="cpu", comm=SerialComm(), exchange="nccl")
    ds = DistributedSimulation(scene, device="cpu", comm=SerialComm())
    with pytest.raises(ValueError, match="exchange='host'"):
        ds.set_exchange("nccl")
    assert ds.exchange == "host"


def test_auto_exchange_takes_nccl_only_with_a_gpu_of_its_own_on_every_rank():
    from polydem.distributed.nccl import auto_exchange, nccl_place

    assert auto_exchange([(True, "GPU-a"), (True, "GPU-b")]) == "nccl"
    assert auto_exchange([(True, "GPU-a"), (True, "GPU-a")]) == "host"  # two ranks on one GPU: NCCL refuses
    assert auto_exchange([(True, "GPU-a"), (False, "GPU-b")]) == "host"  # no nccl4py on one rank
    assert auto_exchange([(True, "GPU-a"), (False, None)]) == "host"  # a CPU rank
    assert auto_exchange([(True, "GPU-a")]) == "host"  # one rank: nothing to send
    import warp as wp

    assert nccl_place(wp.get_device("cpu")) == (False, None)
    assert DistributedSimulation(build("box_pour"), device="cpu", comm=SerialComm()).exchange == "host"


def test_without_nccl4py_the_nccl_exchange_says_how_to_install_it(monkeypatch):
    from polydem.distributed import nccl as nccl_module

    monkeypatch.setitem(sys.modules, "nccl.core", None)  # import nccl.core then raises ImportError
    monkeypatch.setitem(sys.modules, "nccl", None)
    with pytest.raises(RuntimeError, match=r"pip install 'polydem\[nccl\]'.*exchange='host'"):
        nccl_module.load_nccl()


def _have_nccl():
    try:
        import nccl.core  # noqa: F401
    except ImportError:
        return False
    import warp as wp

    return wp.get_cuda_device_count() >= 2


@needs_mpi
@pytest.mark.skipif(not _have_mpi() or not _have_nccl(), reason="needs nccl4py and two GPUs (a GPU per rank)")
@pytest.mark.parametrize("scene, steps, overlap", [("box_pour", 3000, True), ("box_pour", 3000, False),
                                                   ("chain", 1500, True)])  # fmt: skip
def test_nccl_exchange_is_the_undivided_run(tmp_path, scene, steps, overlap):
    """Ghost rows from GPU to GPU with NCCL, in the steps' graphs (split or not): the undivided run's bits."""
    out = tmp_path / "run.npz"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]))
    cmd = [_mpiexec(), "-n", "2", sys.executable, str(HERE / "mpi_job.py"), scene, str(steps), "0.004"]
    cmd += ["cuda", str(out), "50", str(int(overlap)), "nccl"]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    got = np.load(out)
    if scene != "chain":
        assert int(got["partitions"]) > 1, "the run should have moved bodies between ranks"
    assert np.all(got["split"]) if overlap else not np.any(got["split"])
    sim = Simulation(build(scene), device="cuda:0")
    sim.step(steps)
    damping = sim.current_state.body_damping.numpy()
    np.testing.assert_array_equal(got["damping"], damping[got["damping_index"]])
    for k, v in sim.state().items():
        np.testing.assert_array_equal(got[f"state_{k}"], v, err_msg=k)
    for k, v in sim.contacts().items():
        np.testing.assert_array_equal(got[f"contacts_{k}"], v, err_msg=k)


@needs_mpi
@pytest.mark.parametrize(
    "scene, steps, margin, ranks, chunk, overlap",
    [
        ("box_pour", 3000, 0.004, 2, 50, True),  # a small margin: bodies move to other ranks many times
        ("box_pour", 3000, 0.004, 2, 50, False),  # the ghosts exchanged after the whole step
        ("box_pour", 3000, 0.004, 4, 50, True),
        ("box_pour", 3000, 0.002, 2, 1000, True),  # chunks past the margin: stepped again after a new partition
        ("box_pour_long", 3000, 0.004, 2, 50, True),  # damping loads above the share: the ghosts' from their owners
        ("box_pour_long", 3000, 0.002, 2, 1000, True),  # ... also after a redone chunk (restore, then exchange)
        ("mixer", 2450, 0.01, 2, 50, True),  # turning mesh walls (no split), non-convex grains (11 contacts)
        ("chain", 1500, 0.05, 2, 50, True),  # a pulse through contacts across the boundary
        ("chain", 1500, 0.05, 4, 50, True),
    ],
)
def test_decomposed_run_is_the_undivided_run(tmp_path, device, scene, steps, margin, ranks, chunk, overlap):
    """Every rank's state and contacts are the one-process run's, bit for bit, with the ghosts sent while the
    step runs (its first part: the contacts, forces and new state of the bodies sent) and without."""
    out = tmp_path / "run.npz"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]))
    cmd = [_mpiexec(), "-n", str(ranks), sys.executable, str(HERE / "mpi_job.py"), scene, str(steps)]
    cmd += [str(margin), device, str(out), str(chunk), str(int(overlap))]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    got = np.load(out)
    if scene != "chain":  # the chain's bodies hardly move: one partition all along
        assert int(got["partitions"]) > 1, "the run should have moved bodies between ranks"
    assert np.all(got["owned"] > 0)
    # The split step is what ran where it applies: with overlap, on every rank at every check, but with mesh walls.
    assert np.all(got["split"]) if overlap and scene != "mixer" else not np.any(got["split"])
    if chunk > 100:
        assert int(got["redone"]) > 0, "chunks past the margin should have been stepped again"

    sim = Simulation(build(scene), device=device)
    sim.step(steps)
    # Each rank's damping loads, its ghosts' too, are the undivided run's (a ghost's contacts are its owner's).
    damping = sim.current_state.body_damping.numpy()
    assert np.any(damping > 0.0)
    np.testing.assert_array_equal(got["damping"], damping[got["damping_index"]])
    if scene == "box_pour_long":
        assert np.max(damping) > DAMPING_SHARE
    want_state, want_contacts, want_energy = sim.state(), sim.contacts(), sim.energy()
    for k, v in want_state.items():
        np.testing.assert_array_equal(got[f"state_{k}"], v, err_msg=k)
    assert len(want_contacts["body_a"]) > 10
    for k, v in want_contacts.items():
        np.testing.assert_array_equal(got[f"contacts_{k}"], v, err_msg=k)
    for k, v in want_energy.items():  # sums over ranks: equal to rounding
        assert abs(float(got[f"energy_{k}"]) - v) <= 1e-12 * max(1.0, abs(v)), k


@needs_mpi
def test_command_on_two_ranks_writes_the_undivided_run(tmp_path):
    """``mpiexec -n 2 polydem run``: one set of outputs, a checkpoint equal to the one-process run's,
    and checkpoints that resume across the two (1 -> 2 ranks and 2 -> 1)."""
    scene = str(HERE.parent / "scenes" / "default.toml")

    def run(ranks, out, duration, resume=None):
        cmd = [sys.executable, "-m", "polydem", "run", scene, "--duration", str(duration), "--out", str(out), "-q"]
        cmd += ["--device", "cpu"] + (["--resume", str(resume)] if resume else [])
        if ranks > 1:
            cmd = [_mpiexec(), "-n", str(ranks), *cmd]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
        return done.stdout, np.load(out / "checkpoints" / "final.npz")

    # The time too between one and two ranks, not after resuming: Simulation adds up dt per chunk of its
    # own, and a resumed run's chunks differ from the unbroken run's (the last bits of the sum).
    fields = ("body_q", "body_v", "body_w", "body_dissipated", "wall_turn", "wall_xi", "steps_done")
    fields += ("pair_key", "pair_xi", "pair_turn")
    _, one = run(1, tmp_path / "one", 0.02)
    text, two = run(2, tmp_path / "two", 0.02)
    assert "decomposed over 2 ranks" in text and "ghosts exchanged through host memory" in text  # CPU ranks
    assert (tmp_path / "two" / "summary.json").is_file() and (tmp_path / "two" / "default.usd").is_file()
    for k in (*fields, "time"):
        np.testing.assert_array_equal(one[k], two[k], err_msg=k)
    _, straight = run(1, tmp_path / "straight", 0.04)
    _, from_two = run(1, tmp_path / "from_two", 0.04, resume=tmp_path / "two" / "checkpoints" / "final.npz")
    _, from_one = run(2, tmp_path / "from_one", 0.04, resume=tmp_path / "one" / "checkpoints" / "final.npz")
    for k in fields:
        np.testing.assert_array_equal(straight[k], from_two[k], err_msg=k)
        np.testing.assert_array_equal(straight[k], from_one[k], err_msg=k)


@needs_mpi
def test_an_error_on_one_rank_stops_every_rank(tmp_path):
    """Only rank 0 checks the output folder: its error must end the run on every rank, not leave the
    others waiting. The ranks agree before the run: exit code 2 on every rank, and rank 0's one line, as a
    run of one process prints it (no line per rank, no MPI_Abort)."""
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("x")
    scene = str(HERE.parent / "scenes" / "default.toml")
    cmd = [_mpiexec(), "-n", "2", sys.executable, "-m", "polydem", "run", scene, "--out", str(not_a_folder)]
    done = subprocess.run(cmd + ["--device", "cpu", "-q"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert (
        done.stderr == f"polydem: error: {not_a_folder}: --out: the output folder is a file; give a folder with --out\n"
    )
    assert not_a_folder.read_text() == "x"


@needs_mpi
def test_the_nccl_exchange_on_cpu_ranks_is_a_user_error(tmp_path):
    """``--exchange nccl`` sends the rows from GPU to GPU: on CPU ranks every rank stops before the run with one
    line naming the option (exit code 2), nothing written."""
    scene = str(HERE.parent / "scenes" / "default.toml")
    out = tmp_path / "out"
    cmd = [_mpiexec(), "-n", "2", sys.executable, "-m", "polydem", "run", scene, "--out", str(out)]
    done = subprocess.run(cmd + ["--device", "cpu", "-q", "--exchange", "nccl"], capture_output=True, text=True,
                          timeout=300)  # fmt: skip
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr == (
        "polydem: error: --exchange: nccl sends the ghost rows from GPU to GPU, but this rank runs on cpu: run on "
        "GPUs (--device cuda, one per rank) or leave --exchange at host\n"
    )
    assert not out.exists()
