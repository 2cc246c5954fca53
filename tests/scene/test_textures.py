"""Tests of ``controlgs_adapter.scene.textures``: the built-in photographs (scikit-image's, some tinted, each with
its licence) and the mip pyramid built from them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.scene import TEXTURES, load_texture, mip_pyramid

pytest.importorskip("skimage")

F64 = torch.float64


def test_mip_pyramid_halves_with_the_triangle_filter_and_keeps_the_mean():
    # 1 x 4 row [1, 0, 0, 0] -> 1 x 2: the antialiased bilinear (triangle) filter at scale 2 weighs input
    # pixels at distance 0.5, 0.5, 1.5 from output 0's centre by 1 - d/2 = 0.75, 0.75, 0.25 (renormalised:
    # 1.75), so output 0 = 0.75 / 1.75 = 3/7; a plain bilinear resize would give 0.5
    row = torch.tensor([[[1.0, 0.0, 0.0, 0.0]]], dtype=F64).expand(3, 1, 4)
    levels = mip_pyramid(row)
    assert [tuple(lvl.shape) for lvl in levels] == [(3, 1, 4), (3, 1, 2), (3, 1, 1)]
    np.testing.assert_allclose(levels[1][0, 0].numpy(), [3 / 7, 0.0], atol=1e-12)
    tex = torch.rand(3, 37, 20, dtype=F64, generator=torch.Generator().manual_seed(0))
    levels = mip_pyramid(tex)
    assert [tuple(lvl.shape[1:]) for lvl in levels[:3]] == [(37, 20), (19, 10), (10, 5)] and levels[-1].shape[1:] == (1, 1)
    np.testing.assert_allclose(levels[-1].reshape(3).numpy(), tex.mean(dim=(1, 2)).numpy(), atol=0.02)
    assert mip_pyramid(torch.ones(3, 1, 1, dtype=F64))[0].shape == (3, 1, 1) and len(mip_pyramid(torch.ones(3, 1, 1))) == 1


def test_textures_have_a_recorded_licence():
    for name, info in TEXTURES.items():
        assert "CC0" in info.licence or "public domain" in info.licence
        t = load_texture(name)
        assert t.shape[0] == 3 and 0.0 <= float(t.min()) and float(t.max()) <= 1.0


def test_textures_are_the_skimage_photographs_tinted():
    import skimage.data

    for name in ("astronaut", "chelsea"):
        t = load_texture(name)
        ref = skimage.data.__dict__[name]().astype(np.float64) / 255.0
        assert t.dtype == F64
        np.testing.assert_array_equal(t.numpy(), ref.transpose(2, 0, 1))
    tints = {"brick": (0.92, 0.55, 0.42), "grass": (0.55, 0.85, 0.35), "gravel": (0.85, 0.80, 0.70)}
    for name, tint in tints.items():
        assert TEXTURES[name].tint == tint
        t = load_texture(name)
        grey = skimage.data.__dict__[name]().astype(np.float64) / 255.0
        np.testing.assert_allclose(t.numpy(), grey[None] * np.asarray(tint)[:, None, None], rtol=0, atol=1e-15)
    assert [n for n, i in TEXTURES.items() if i.tint is None] == ["astronaut", "coffee", "chelsea", "rocket"]
    # a fresh copy every time: editing one does not change the next
    t = load_texture("coffee")
    t.zero_()
    assert float(load_texture("coffee").max()) > 0.5
    with pytest.raises(InputValueError, match=r"texture.*got 'lena'"):
        load_texture("lena")
