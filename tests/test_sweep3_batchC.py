"""Misses of the fresh sample of 2026-11-23 evening (seed 11230001): lens map inversion, Blender poses,
Octree-GS anchor PLY, Scaffold-GS cfg_args, report heatmap labels, each pinned by what the code is for."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_io import save_scaffold_dir
from controlgs_adapter.datasets.blender import opengl_c2w_to_w2c
from controlgs_adapter.downstream.lens import invert_map
from controlgs_adapter.formats.backbone import read_cfg_args, read_ply, write_ply

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace in the saved formats


# ------------------------------------------------------------------------------ lens: invert_map
def test_one_newton_step_inverts_an_affine_map_exactly():
    """A bilinearly interpolated affine map is affine everywhere, so Newton's method (float64, central
    differences) lands on the analytic inverse ``A^-1 (q - b)`` in one step, for every channel; the y column
    of the Jacobian matters because the map shears y into x."""
    a = torch.tensor([[1.5, 0.6], [0.4, 2.0]], dtype=torch.float64)
    b = torch.tensor([0.1, -0.2], dtype=torch.float64)
    gh, gw = 5, 6
    ys = (torch.arange(gh, dtype=torch.float64) + 0.5) * (2.0 / gh) - 1.0
    xs = (torch.arange(gw, dtype=torch.float64) + 0.5) * (2.0 / gw) - 1.0
    p = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # [Gh, Gw, 2] (x, y)
    fmap = (p @ a.T + b).expand(3, -1, -1, -1).contiguous()
    h, w = 7, 9
    qy = (torch.arange(h, dtype=torch.float64) + 0.5) * (2.0 / h) - 1.0
    qx = (torch.arange(w, dtype=torch.float64) + 0.5) * (2.0 / w) - 1.0
    q = torch.stack(torch.meshgrid(qx, qy, indexing="xy"), dim=-1)
    expected = torch.linalg.solve(a, (q - b).reshape(-1, 2).T).T.reshape(h, w, 2)
    g = invert_map(fmap, (h, w), iterations=1, tol=0.0)
    assert g.dtype == torch.float64 and g.shape == (3, h, w, 2)
    assert float((g - expected).abs().max()) < 2e-10


# ------------------------------------------------------------------------------ Blender poses
def test_blender_pose_is_inverted_in_float64_even_from_a_float32_matrix():
    """The docstring promises the rigid inverse (``R^T``, ``-R^T t``) in float64, then float32: a float32 ``transform_matrix`` of a
    camera far from the origin looking back at it gives the correctly rounded world-to-camera matrix, whose
    x and y translation (a cancellation of terms in the thousands) stay near zero."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        centre = rng.uniform(-3000.0, 3000.0, 3)
        z_gl = centre / np.linalg.norm(centre)  # OpenGL: the camera looks along -z, here at the origin
        x = np.cross([0.0, 0.0, 1.0], z_gl)
        x /= np.linalg.norm(x)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([x, np.cross(z_gl, x), z_gl], axis=1)
        c2w[:3, 3] = centre
        c2w32 = c2w.astype(np.float32)
        ref = c2w32.astype(np.float64)
        ref[:3, 1:3] *= -1.0  # OpenGL -> OpenCV camera axes
        rot = ref[:3, :3]
        w2c_ref = np.eye(4)
        w2c_ref[:3, :3] = rot.T  # the documented rigid inverse R^T, -R^T t, each entry summed in float64
        w2c_ref[:3, 3] = [-sum(rot[k, i] * ref[k, 3] for k in range(3)) for i in range(3)]
        got = opengl_c2w_to_w2c(c2w32)
        assert got.dtype == torch.float32
        np.testing.assert_allclose(got.numpy().astype(np.float64), w2c_ref, rtol=1e-7, atol=1e-6)


# ------------------------------------------------------------------------------ Octree-GS anchor PLY
def test_octree_gs_anchor_ply_keeps_six_scales_when_other_tools_add_scale_columns(tmp_path):
    """Octree-GS anchors have six scales (``scale_0..5``: offset extent and Gaussian size); a PLY carrying a
    further ``scale_6`` column (appended by another tool) still loads as ``[A, 6]`` from the first six."""
    from test_backend_octree_gs import _arrays, _decoders, _write_dir

    from controlgs_adapter.backends.octree_gs import load_octree_gs_dir

    arr = _arrays(1)
    _write_dir(tmp_path, arr, _decoders(torch.Generator().manual_seed(1)))
    ply = tmp_path / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {**fields, "scale_6": np.full(len(fields["x"]), 9.0, np.float32)})
    model = load_octree_gs_dir(tmp_path)
    assert torch.equal(model._scaling, torch.from_numpy(arr["scale"]))


# ------------------------------------------------------------------------------ Scaffold-GS cfg_args
def test_saved_scaffold_cfg_args_records_scaffold_gs_default_undistorted_false(tmp_path):
    """``cfg_args`` is Scaffold-GS's ``ModelParams`` as its ``train.py`` records them; Scaffold-GS defaults
    ``undistorted = False`` (the images were not undistorted by it), and a model made here was not either."""
    torch.manual_seed(0)
    model = NeuralGaussianModel(5, feat_dim=4, n_offsets=2, voxel_size=0.05)
    save_scaffold_dir(model, tmp_path, 10, mlp_mode="unite")
    cfg = read_cfg_args(tmp_path / "cfg_args")
    assert cfg["undistorted"] is False
    assert (cfg["feat_dim"], cfg["n_offsets"]) == (4, 2)


# ------------------------------------------------------------------------------ report heatmaps
def test_heatmap_cell_labels_carry_the_sign_of_the_difference(tmp_path, monkeypatch):
    """The heatmaps show method minus baseline; each cell's label is signed (``+0.50`` where the method gains,
    ``-0.25`` where it loses), in the metric's format (PSNR: two decimals), at that cell's (column, row)."""
    from matplotlib.figure import Figure

    from controlgs_adapter.evaluation import GridResult
    from controlgs_adapter.report import plot_heatmaps

    labels: list[tuple[float, float, str]] = []
    save = Figure.savefig

    def recording_savefig(fig, *args, **kwargs):
        for ax in fig.axes:
            labels.extend((t.get_position()[0], t.get_position()[1], t.get_text()) for t in ax.texts)
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", recording_savefig)
    ss = torch.full((2, 3, 1), 20.0, dtype=torch.float64)
    delta = torch.tensor([[0.5, -0.25, 0.0], [1.0, 2.0, -3.0]], dtype=torch.float64)[..., None]
    r = GridResult((1.0, 2.0), (0.0, 0.2, 0.4), {"ss": {"psnr": ss}, "controlgs": {"psnr": ss + delta}})
    plot_heatmaps(r, tmp_path / "h.png", baselines=("ss",))
    assert sorted(labels) == sorted([(0, 0, "+0.50"), (1, 0, "-0.25"), (2, 0, "+0.00"),
                                     (0, 1, "+1.00"), (1, 1, "+2.00"), (2, 1, "-3.00")])


def test_saving_over_a_model_succeeds_when_the_old_folder_cannot_be_removed(tmp_path):
    """Saving over an existing iteration folder renames the old one aside, moves the new one into place, then
    removes the old one as a best effort: a file there that cannot be deleted (here an immutable one, which
    root cannot delete either) leaves the old copy behind but does not turn the finished save into an error."""
    import shutil
    import subprocess

    from controlgs_adapter.backends.scaffold_io import load_scaffold_dir

    if shutil.which("chattr") is None:
        pytest.skip("needs chattr to make an undeletable file")
    torch.manual_seed(0)
    old = NeuralGaussianModel(5, feat_dim=4, n_offsets=2, voxel_size=0.05)
    folder = save_scaffold_dir(old, tmp_path, 10, mlp_mode="unite")
    stuck = folder / "notes.txt"
    stuck.write_text("kept by the user")
    if subprocess.run(["chattr", "+i", str(stuck)], capture_output=True).returncode != 0:
        pytest.skip("this filesystem cannot mark a file immutable")
    try:
        new = NeuralGaussianModel(7, feat_dim=4, n_offsets=2, voxel_size=0.05)
        assert save_scaffold_dir(new, tmp_path, 10, mlp_mode="unite") == folder
        assert load_scaffold_dir(tmp_path).num_anchors == 7
        left = [p for p in (tmp_path / "point_cloud").iterdir() if p.name.startswith(".iteration_10.old.")]
        assert len(left) == 1 and (left[0] / "iteration_10" / "notes.txt").is_file()
    finally:
        for p in tmp_path.rglob("notes.txt"):
            subprocess.run(["chattr", "-i", str(p)], capture_output=True)
