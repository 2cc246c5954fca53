"""Misses of the fresh sample of 2026-11-23 evening (seed 11230001): plane renderer window, camera
rigidity check, LUT pre-warp buffers, heatmap colour range, weights-only loading of GPU checkpoints,
the grid evaluation's progress bar, each pinned by what the code is for."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import GridResult, evaluate_grid
from controlgs_adapter.formats.backbone import load_state_dict_file
from controlgs_adapter.report import plot_heatmaps
from controlgs_adapter.scene.planes import TexturedPlane, render_planes
from controlgs_adapter.state import Camera
from controlgs_adapter.downstream.lens import DisplayLUTMap


def _camera(rot: torch.Tensor, t: tuple[float, float, float], f: float = 40.0, size: int = 32) -> Camera:
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = rot
    w2c[:3, 3] = torch.tensor(t, dtype=torch.float64)
    k = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Camera(w2c, k, size, size)


# ------------------------------------------------------------------------------ plane renderer
def test_plane_seen_by_a_translated_camera_covers_its_projected_rectangle():
    """A 1 x 1 fronto-parallel plane at depth 4 seen by a camera whose world-to-camera translation is
    (0.3, 0, 0): in camera space it spans x in [-0.2, 0.8], y in [-0.5, 0.5], so with f = 40, c = 16 it
    covers pixels u in [14, 24), v in [11, 21) exactly (edges on pixel boundaries): 100 pixels, depth 4."""
    plane = TexturedPlane("p", torch.tensor([0.0, 0.0, 4.0]), torch.tensor([0.5, 0.0, 0.0]),
                          torch.tensor([0.0, 0.5, 0.0]), torch.full((3, 8, 8), 0.5))
    cam = _camera(torch.eye(3, dtype=torch.float64), (0.3, 0.0, 0.0))
    image, coverage, depth = render_planes([plane], cam, samples=4)
    want = torch.zeros(1, 32, 32, dtype=torch.float64)
    want[:, 11:21, 14:24] = 1.0
    assert torch.equal(coverage, want)
    assert torch.allclose(depth[want > 0], torch.full((100,), 4.0, dtype=torch.float64), atol=1e-12)
    assert float(depth[want == 0].abs().max()) == 0.0


# ------------------------------------------------------------------------------ camera rigidity
def test_camera_refuses_a_rotation_0_15_percent_off_orthonormal_and_accepts_float32_round_off():
    """``world_to_camera`` must be rigid: a rotation block whose R R^T is 1.5e-3 off the identity (a scale
    of 1.00075 on one axis) is refused; 5e-4 off (float32 round-off of a composed pose and more) passes."""
    off = torch.diag(torch.tensor([1.00075, 1.0, 1.0], dtype=torch.float64))
    with pytest.raises(InputValueError, match="orthonormal"):
        _camera(off, (0.0, 0.0, 0.0))
    near = torch.diag(torch.tensor([1.00025, 1.0, 1.0], dtype=torch.float64))
    assert _camera(near, (0.0, 0.0, 0.0)).width == 32


# ------------------------------------------------------------------------------ LUT pre-warp
def test_display_lut_tables_are_held_outside_the_callers_graph():
    """Tables built from tensors that require grad (a fitted table straight from the optimiser) become
    plain buffers: no gradient flows back to the caller's tensors and none is tracked."""
    disp = torch.zeros(3, 4, 5, 2, requires_grad=True)
    gain = torch.ones(3, 4, 5, requires_grad=True)
    lut = DisplayLUTMap({"exact": (disp, gain)})
    for name in ("displacement_exact", "gain_exact"):
        buf = getattr(lut, name)
        assert not buf.requires_grad and buf.grad_fn is None, name
    assert torch.equal(lut.gain_exact, torch.ones(3, 4, 5))


# ------------------------------------------------------------------------------ heatmap colour range
def test_heatmap_colour_range_spans_the_largest_difference(tmp_path):
    """The colour scale of each panel is symmetric at the largest |difference|: a cell of +5 dB next to a
    cell of +10 dB is drawn in the colour half-way up the positive side (RdBu at 0.75), not saturated."""
    import matplotlib
    import matplotlib.image

    ss = torch.full((2, 2, 1), 20.0, dtype=torch.float64)
    delta = torch.tensor([[10.0, 5.0], [0.0, -10.0]], dtype=torch.float64)[..., None]
    r = GridResult((1.0, 2.0), (0.0, 0.2), {"ss": {"psnr": ss}, "controlgs": {"psnr": ss + delta}})
    img = torch.from_numpy(matplotlib.image.imread(plot_heatmaps(r, tmp_path / "h.png")))[..., :3].double()
    mid = torch.tensor(matplotlib.colormaps["RdBu"](0.75)[:3], dtype=torch.float64)
    full = torch.tensor(matplotlib.colormaps["RdBu"](1.0)[:3], dtype=torch.float64)
    n_mid = int(((img - mid).abs().amax(-1) < 0.02).sum())
    n_full = int(((img - full).abs().amax(-1) < 0.02).sum())
    # one cell each (about 100 x 100 px, less its label); the colour bar alone holds a few hundred
    assert n_mid > 3000 and n_full > 3000, (n_mid, n_full)


# ------------------------------------------------------------------------------ weights-only loading
_SAVE_AS_CUDA = """
import sys, torch
# tag every storage as if it had been saved on a GPU (this machine may have none)
torch.serialization.register_package(1, lambda obj: "cuda:0" if obj.device.type == "cpu" else None,
                                     lambda obj, location: None)
torch.save({"w": torch.arange(6, dtype=torch.float32).reshape(2, 3), "n": 3}, sys.argv[1])
"""


def test_state_dict_saved_on_a_gpu_loads_onto_the_cpu(tmp_path):
    """``load_state_dict_file`` reads on the CPU: a checkpoint whose tensors were saved on ``cuda:0`` loads
    with CPU tensors, whether or not this machine has a GPU."""
    path = tmp_path / "gpu.pt"
    subprocess.run([sys.executable, "-c", _SAVE_AS_CUDA, str(path)], check=True, timeout=120)
    assert b"cuda:0" in path.read_bytes()
    obj = load_state_dict_file(path)
    assert obj["n"] == 3 and obj["w"].device == torch.device("cpu")
    assert torch.equal(obj["w"], torch.arange(6, dtype=torch.float32).reshape(2, 3))


# ------------------------------------------------------------------------------ evaluation progress bar
def test_evaluate_grid_shows_its_progress_bar_by_default(tiny, capsys):
    """``evaluate_grid`` reports its progress ("evaluating grid", on stderr) unless ``progress=False``."""
    scene, model = tiny
    views = scene.data.views("train", first=1)
    kw = dict(downsample=(1.0,), power_saving=(0.0,), baselines=(), extra_metrics=False)
    capsys.readouterr()
    evaluate_grid(model, views, {}, **kw)
    assert "evaluating grid" in capsys.readouterr().err
    evaluate_grid(model, views, {}, progress=False, **kw)
    assert "evaluating grid" not in capsys.readouterr().err



# ------------------------------------------------------------------------------ a peer that died
_RANK = """
import json, os, sys, time, torch
from torch import nn
from controlgs_adapter.distributed import DistributedError, init_distributed
rank, port = sys.argv[1], sys.argv[2]
os.environ.update({"RANK": rank, "WORLD_SIZE": "2", "LOCAL_RANK": rank, "MASTER_ADDR": "127.0.0.1",
                   "MASTER_PORT": port})
ctx = init_distributed("gloo", timeout=5.0)
if rank == "1":
    os._exit(0)  # dies without a word
time.sleep(1.0)
out = {}
try:
    ctx.all_gather_json({"a": 1})
except DistributedError as e:
    out["gather"] = str(e)
p = nn.Parameter(torch.zeros(2))
p.grad = torch.ones(2)
try:
    ctx.sync_gradients([p], step=7)
except DistributedError as e:
    out["sync"] = str(e)
print(json.dumps(out))
os._exit(0)
"""


def test_a_dead_peer_is_reported_with_the_collective_and_iteration(tmp_path):
    """When the other process dies, each collective fails with a message naming this rank, what it was
    doing and (for the gradient exchange) the iteration, so that the user knows where the run stopped."""
    import json
    import os
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    procs = [subprocess.Popen([sys.executable, "-c", _RANK, r, port], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for r in ("0", "1")]
    (out0, err0), _ = (p.communicate(timeout=120) for p in procs)
    msgs = json.loads(out0.strip().splitlines()[-1])
    assert msgs["gather"].startswith("rank 0 of 2: gathering results failed ("), msgs
    assert msgs["sync"].startswith("rank 0 of 2: the gradient all-reduce at iteration 7 failed ("), msgs
    assert "no checkpoint was written yet" in msgs["sync"]


# ------------------------------------------------------------------------------ spacing of a large cloud
@pytest.mark.slow
def test_median_spacing_of_a_cloud_past_2_24_points():
    """``median_spacing`` works on clouds of any size, also past 2^24 points (where fewer than one row of
    distances fits the 2^24 chunk): points every 0.5 on a line have a nearest neighbour at 0.5."""
    from controlgs_adapter.backends.models.reference_model import median_spacing

    n = (1 << 24) + 1
    pts = torch.zeros(n, 3, dtype=torch.float64)
    pts[:, 0] = torch.arange(n, dtype=torch.float64) * 0.5
    assert median_spacing(pts, samples=2) == 0.5
