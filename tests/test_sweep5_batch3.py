"""Mutation sweep 5, batch 3: behaviours that a plausible one-line bug changed and no test observed (a
textured plane refusing a non-finite photograph, COLMAP text image names holding spaces, the PSF-bank
builder silent unless asked). See docs/testing.md."""

from __future__ import annotations

import pytest
import torch

from _scene_writers import save_png
from controlgs_adapter.errors import InputValueError

D = torch.float64


# ----------------------------------------------------------------------------- textured plane: finite texture
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_textured_plane_refuses_a_non_finite_texture_naming_it(bad):
    """``TexturedPlane``'s texture is an sRGB photograph in [0, 1] (its docstring): one NaN or Inf texel
    would spread through every mip level above it and blank the plane's renders, so the constructor
    refuses it, naming the texture, as it does non-finite geometry. A finite texture is accepted."""
    from controlgs_adapter.scene.planes import TexturedPlane

    c, r, d = torch.tensor([0.0, 0.0, 4.0]), torch.tensor([0.5, 0.0, 0.0]), torch.tensor([0.0, 0.5, 0.0])
    tex = torch.full((3, 4, 4), 0.5, dtype=D)
    TexturedPlane("ok", c, r, d, tex)
    tex[1, 2, 3] = bad
    with pytest.raises(InputValueError, match=r"texture contains 1 non-finite value"):
        TexturedPlane("p", c, r, d, tex)


# ----------------------------------------------------------------------------- COLMAP images.txt: names with spaces
def test_colmap_text_image_names_may_hold_spaces(tmp_path):
    """COLMAP's ``images.txt`` line is ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` with NAME last (COLMAP's
    "Output format" page): the name is the rest of the line, and a photo named ``my photo 2.png`` (spaces
    are common in users' file names; the binary format stores it as a C string) must be read as that name,
    with its pose and camera, not refused as a line with too many fields. Written by hand: identity
    rotation, t = (0.25, -0.5, 3), a PINHOLE 4 x 3 camera."""
    from controlgs_adapter.datasets.colmap import read_colmap

    name = "my photo 2.png"
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("# Camera list\n1 PINHOLE 4 3 5.0 6.0 2.0 1.5\n")
    (sparse / "images.txt").write_text(f"# Image list\n7 1 0 0 0 0.25 -0.5 3 1 {name}\n\n")
    save_png(tmp_path / "images" / name, torch.full((3, 3, 4), 0.5))

    scene = read_colmap(tmp_path, holdout=0)
    (frame,) = scene.splits["train"]
    assert frame.name == name and frame.source == tmp_path / "images" / name
    w2c = torch.eye(4)
    w2c[:3, 3] = torch.tensor([0.25, -0.5, 3.0])
    assert torch.equal(frame.camera.world_to_camera, w2c)
    assert torch.equal(frame.camera.intrinsics, torch.tensor([[5.0, 0.0, 2.0], [0.0, 6.0, 1.5], [0.0, 0.0, 1.0]]))
    assert (frame.camera.width, frame.camera.height) == (4, 3)


# ----------------------------------------------------------------------------- build_bank: silent by default
def test_build_bank_prints_nothing_unless_progress_is_asked(capsys):
    """``build_bank``'s docstring: ``progress=True`` prints one line per traced wavelength to stdout (the
    ``controlgs optics build-bank`` command turns it on); by default a library call prints nothing. A tiny
    bank (one field, 5 x 5 PSFs) both ways: silent, then one ``traced <nm> nm`` line per wavelength."""
    from controlgs_adapter.downstream.optics.generate import build_bank

    kw = dict(grid=(1, 1), psf_size=5, pupil_samples=8, chief_grid=(2, 2))
    bank = build_bank(**kw)
    out = capsys.readouterr()
    assert (out.out, out.err) == ("", "")
    assert build_bank(**kw, progress=True).wavelengths_nm == bank.wavelengths_nm
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split(" nm:")[0].split()[-1] for ln in lines] == [f"{w:g}" for w in bank.wavelengths_nm]
