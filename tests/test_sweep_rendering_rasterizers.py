"""Rasterizer selection's branches pinned (issue 15 section 5): dtype refusals, the environment
variable and the context's precedence, the automatic choice's refusal listing every reason, the
version parse of gsplat's alpha clamp, the gsplat adaptor's empty scene, and ``rasterize_gaussians``'s
explicit choice."""

from __future__ import annotations

import types
from typing import Any

import pytest
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering import rasterizers
from controlgs_adapter.rendering.rasterizers import (RASTERIZER_ENV, GsplatRasterizer, Rasterizer, TorchSplatter,
                                                     gsplat_alpha_max, rasterize_gaussians, select_rasterizer,
                                                     use_rasterizer)
from controlgs_adapter.rendering.splatter import rasterize
from controlgs_adapter.state import Camera

CPU, CUDA = torch.device("cpu"), torch.device("cuda")


def _scene(dtype: torch.dtype = torch.float32) -> tuple[list[torch.Tensor], Camera]:
    k = torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 3.0], [0.0, 0.0, 1.0]])
    cam = Camera(torch.eye(4), k, 8, 6)
    g = [torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 3.0]]), torch.full((2, 3), 0.2), torch.tensor([[1.0, 0, 0, 0]] * 2),
         torch.tensor([0.7, 0.9]), torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])]
    return [t.to(dtype) for t in g], cam


def test_env_name_and_base_class() -> None:
    assert RASTERIZER_ENV == "CONTROLGS_RASTERIZER"
    assert repr(TorchSplatter()) == "TorchSplatter(name='torch')" and GsplatRasterizer.name == "gsplat"
    base = Rasterizer()
    with pytest.raises(NotImplementedError):
        base.unavailable(CPU, torch.float32)
    with pytest.raises(NotImplementedError):
        base(*_scene()[0], _scene()[1])


def test_torch_splatter_dtypes() -> None:
    t = TorchSplatter()
    assert t.unavailable(CPU, torch.float32) is None and t.unavailable(CPU, torch.float64) is None
    assert t.unavailable(CUDA, torch.float32) is None  # any device
    assert t.unavailable(CPU, torch.float16) == "needs float32 or float64, got torch.float16"
    assert t.unavailable(CPU, torch.bfloat16) == "needs float32 or float64, got torch.bfloat16"


def test_gsplat_unavailable_reasons(monkeypatch: pytest.MonkeyPatch) -> None:
    g = GsplatRasterizer()
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: types.SimpleNamespace())
    assert g.unavailable(CPU, torch.float32) == "runs on CUDA devices only, not cpu"
    assert g.unavailable("cpu", torch.float32) == "runs on CUDA devices only, not cpu"  # a device name works too
    assert g.unavailable(CUDA, torch.float64) == "needs float32, got torch.float64"
    assert g.unavailable(CUDA, torch.float32) is None
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: "gsplat does not import (x)")
    assert g.unavailable(CUDA, torch.float32) == "gsplat does not import (x)"
    with pytest.raises(InputValueError, match=r"rasterizer 'gsplat': gsplat does not import \(x\)"):
        g(*_scene()[0], _scene()[1])


def test_import_gsplat_reports_a_broken_install(monkeypatch: pytest.MonkeyPatch) -> None:
    def boom(name: str) -> Any:
        raise OSError("libcudart.so: cannot open")

    rasterizers._import_gsplat.cache_clear()
    monkeypatch.setattr(rasterizers.importlib, "import_module", boom)
    try:
        assert rasterizers._import_gsplat() == ("gsplat does not import (OSError: libcudart.so: cannot open); install it "
                                                "with 'pip install --no-deps gsplat'")
    finally:
        rasterizers._import_gsplat.cache_clear()


def test_gsplat_alpha_max_parses_major_and_minor_as_numbers() -> None:
    assert gsplat_alpha_max("1.10.0") == 0.99  # minor 10 > 6 (a string comparison would say otherwise)
    assert gsplat_alpha_max("1.6") == 0.99 and gsplat_alpha_max("1.5.99") == 0.999
    assert gsplat_alpha_max("0.9.0") == 0.999 and gsplat_alpha_max("2.0") == 0.99
    assert gsplat_alpha_max("0") == 0.999 and gsplat_alpha_max("dev") == 0.999  # unparsable: the old clamp


def test_gsplat_empty_scene_is_the_background_or_black(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: types.SimpleNamespace(__version__="1.6.0"))
    g, cam = _scene()
    empty = [t[:0] for t in g]
    black = GsplatRasterizer()(*empty, cam)
    assert torch.equal(black.color, torch.zeros(3, 6, 8)) and torch.equal(black.alpha, torch.zeros(1, 6, 8))
    assert torch.equal(black.depth, torch.zeros(1, 6, 8)) and black.visible.dtype == torch.bool
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = GsplatRasterizer()(*empty, cam, bg)
    assert torch.equal(out.color[:, 5, 7], bg) and torch.equal(out.color[:, 0, 0], bg)
    out.color[0, 0, 0] = 5.0  # a copy, not a view of the background
    assert float(bg[0]) == pytest.approx(0.1)


def test_selection_precedence(monkeypatch: pytest.MonkeyPatch) -> None:
    class Mine(Rasterizer):
        name = "mine"

        def unavailable(self, device: Any, dtype: Any) -> str | None:
            return None if dtype == torch.float64 else "float64 only"

    mine = Mine()
    monkeypatch.setenv(RASTERIZER_ENV, "nope")
    with pytest.raises(InputValueError, match=r"rasterizer 'nope' is not registered; registered: \['gsplat', 'torch'\] "
                                              r"\(or 'auto'\)"):
        select_rasterizer(CPU)
    with use_rasterizer("torch"):  # the context beats the environment
        assert select_rasterizer(CPU).name == "torch"
        assert select_rasterizer(CPU, torch.float64, mine) is mine  # the argument beats both
        with use_rasterizer(mine):
            assert select_rasterizer(CPU, torch.float64) is mine
            with pytest.raises(InputValueError, match="rasterizer 'mine' cannot render torch.float32 on cpu: float64 only"):
                select_rasterizer(CPU, torch.float32)
        assert select_rasterizer(CPU).name == "torch"  # the inner block's choice is reset
        with use_rasterizer(None):  # None: back to the environment
            with pytest.raises(InputValueError, match="'nope' is not registered"):
                select_rasterizer(CPU)
    with pytest.raises(InputValueError, match="'nope' is not registered"):  # the outer choice is reset too
        select_rasterizer(CPU)
    monkeypatch.setenv(RASTERIZER_ENV, "")
    assert select_rasterizer(CPU).name == "torch"  # empty: auto
    monkeypatch.setenv(RASTERIZER_ENV, "auto")
    assert select_rasterizer("cpu", torch.float64).name == "torch"


def test_auto_refusal_lists_every_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(RASTERIZER_ENV, raising=False)
    monkeypatch.setattr(rasterizers, "_import_gsplat", lambda: types.SimpleNamespace())
    with pytest.raises(InputValueError) as e:
        select_rasterizer(CPU, torch.float16)
    assert str(e.value) == ("no registered rasterizer can render torch.float16 on cpu: gsplat: runs on CUDA devices "
                            "only, not cpu; torch: needs float32 or float64, got torch.float16")
    with pytest.raises(InputValueError, match="'torch' cannot render torch.float16"):
        select_rasterizer(CPU, torch.float16, "torch")


def test_rasterize_gaussians_passes_everything_on() -> None:
    g, cam = _scene(torch.float64)
    bg = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    out = rasterize_gaussians(*g, cam, bg, rasterizer="torch")
    want = rasterize(*g, cam, bg)
    assert out.color.dtype == torch.float64 and torch.equal(out.color, want.color) and torch.equal(out.depth, want.depth)
    seen: list[tuple[Any, ...]] = []

    class Spy(Rasterizer):
        name = "spy"

        def unavailable(self, device: Any, dtype: Any) -> str | None:
            seen.append((device, dtype))
            return None

        def __call__(self, *args: Any) -> Any:
            seen.append(args)
            return "out"

    assert rasterize_gaussians(*g, cam, bg, rasterizer=Spy()) == "out"
    assert seen[0] == (CPU, torch.float64)  # chosen for means' device and dtype
    assert seen[1][5] is cam and seen[1][6] is bg and seen[1][0] is g[0] and seen[1][2] is g[2]
