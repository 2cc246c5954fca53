"""Mutation sweep 5, batch 6: behaviours that a plausible one-line bug changed and no test observed (a
COLMAP camera whose focal length is below one pixel). See docs/testing.md."""

from __future__ import annotations

import pytest
import torch

from _scene_writers import save_png
from controlgs_adapter.errors import FileFormatError


# ----------------------------------------------------------------------------- COLMAP: focal lengths in (0, 1] px
def _scene(tmp_path, fx: float, fy: float):
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"# Camera list\n1 PINHOLE 4 3 {fx!r} {fy!r} 2.0 1.5\n")
    (sparse / "images.txt").write_text("# Image list\n1 1 0 0 0 0 0 0 1 a.png\n\n")
    save_png(tmp_path / "images" / "a.png", torch.full((3, 3, 4), 0.5))
    return tmp_path


def test_colmap_focal_length_below_one_pixel_is_accepted(tmp_path):
    """``read_colmap`` refuses a camera whose focal lengths are not > 0 (its error says "must be > 0"); any
    positive focal length is a valid pinhole camera, including one under a pixel (an extreme fisheye-like
    crop, or a model written in normalised units): PINHOLE fx = 0.5, fy = 0.75 on a 4 x 3 camera and image
    (scale 1) gives K = [[0.5, 0, 2], [0, 0.75, 1.5], [0, 0, 1]] (by hand). fx = 0 is refused."""
    from controlgs_adapter.datasets.colmap import read_colmap

    scene = read_colmap(_scene(tmp_path / "ok", 0.5, 0.75), holdout=0)
    (frame,) = scene.splits["train"]
    assert torch.equal(frame.camera.intrinsics, torch.tensor([[0.5, 0.0, 2.0], [0.0, 0.75, 1.5], [0.0, 0.0, 1.0]]))

    with pytest.raises(FileFormatError, match=r"focal lengths 0\.0, 0\.75 \(must be > 0\)"):
        read_colmap(_scene(tmp_path / "zero", 0.0, 0.75), holdout=0)
