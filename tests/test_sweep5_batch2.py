"""Mutation sweep 5, batch 2: behaviours that a plausible one-line bug changed and no test observed (the
splatter's transmittance carried across depth passes without early termination, the viewer's optics
mode reaching its pipeline, a refused host getting no answer but the 403). See docs/testing.md."""

from __future__ import annotations

import json
import socket
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
import torch

from controlgs_adapter import plugins
from controlgs_adapter.rendering import splatter
from controlgs_adapter.rendering.splatter import rasterize
from controlgs_adapter.rendering.splatter_reference import rasterize_reference

sys.path.insert(0, str(Path(__file__).parent))
from test_splatter import make_camera, random_scene  # noqa: E402

F64 = torch.float64
SIZE = 16
needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")


# ----------------------------------------------------------------------------- splatter: passes without termination
@pytest.mark.parametrize("budget", [64, 1 << 21])
def test_exact_compositing_carries_the_transmittance_across_depth_passes(budget: int, monkeypatch) -> None:
    """``transmittance_min=0`` composites every splat (rasterize's docstring). A chunk whose candidate
    pairs exceed ``_PAIR_BUDGET`` is expanded in several depth passes; each pixel's later passes must start
    from its transmittance after the earlier ones (a pass restarting at T = 1 gives alpha > 1 on a
    crowded pixel). A tiny budget forces many passes on a small image; the float64 brute-force reference
    decides, for the image and for the gradients."""
    monkeypatch.setattr(splatter, "_PAIR_BUDGET", budget)
    cam = make_camera()
    scene = random_scene(5, 60, cam, hard=False)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    weights = torch.randn(5, 17, 23, generator=torch.Generator().manual_seed(2), dtype=F64)

    def run(fn: Any) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        inputs = [t.clone().requires_grad_() for t in scene]
        out = fn(*inputs, cam, bg, transmittance_min=0.0)
        stack = torch.cat([out.color, out.alpha, out.depth])
        return stack.detach(), torch.autograd.grad((stack * weights).sum(), inputs)

    got, got_grads = run(lambda *a, **k: rasterize(*a, tile_size=4, **k))
    ref, ref_grads = run(rasterize_reference)
    assert float(ref[3].max()) > 0.8  # crowded pixels: a pass restarting at T = 1 overshoots them
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-10)
    for g, r in zip(got_grads, ref_grads):
        torch.testing.assert_close(g, r, rtol=1e-8, atol=1e-8)


# ----------------------------------------------------------------------------- the viewer
@pytest.fixture(scope="module")
def viewer_session() -> Any:
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene
    from controlgs_adapter.viewer import ViewerSession

    scene = load_builtin_scene("ar", SIZE, views=4, test_every=4, samples=1)
    return ViewerSession(load_builtin_backbone("ar"), scene.views("test"), {}, name="tiny")


@needs_optics
def test_viewer_renders_with_the_optics_mode_of_the_state(viewer_session: Any) -> None:
    """The state's ``optics`` (distortion, fast) is the optics stage's mode of that render: the
    session's PSNR / SSIM are :func:`evaluate_grid`'s at the same mode (session.render's docstring: "as
    evaluate_grid computes them"), and the modes give different eye images (the pipeline is cached per
    stage set, so a mode that never reached it would leave every render at the first one's)."""
    from controlgs_adapter.evaluation import evaluate_grid
    from controlgs_adapter.viewer import parse_state

    eyes = {}
    for mode in ("distortion", "fast"):
        out = viewer_session.render(parse_state({"downsample": 2.0, "power_saving": 0.2, "optics": mode}, 1))
        ss = next(m for m in out["methods"] if m["name"] == "ss")
        grid = evaluate_grid(viewer_session.model, viewer_session.views, {}, downsample=[2.0], power_saving=[0.2],
                             optics_mode=mode, baselines=("ss",), ideal=False, extra_metrics=False, progress=False)
        for k in ("psnr", "ssim"):
            assert ss["metrics"][k] == pytest.approx(float(grid.per_view["ss"][k][0, 0, 0]), abs=1e-9), (mode, k)
        eyes[mode] = ss["eye"]
    assert eyes["distortion"] != eyes["fast"]


def test_a_refused_host_gets_the_403_and_nothing_else(viewer_session: Any) -> None:
    """A request for another host name is answered 403 and not handled (server._host_ok: DNS rebinding):
    everything the server writes on that connection up to its close is the one 403 answer (a handled
    request would follow it with a second answer, here the scene's info)."""
    from controlgs_adapter.viewer import make_server

    srv = make_server(viewer_session)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        with socket.create_connection(srv.server_address[:2], timeout=60) as sock:
            sock.sendall(b"GET /api/info HTTP/1.1\r\nHost: evil.example\r\nConnection: close\r\n\r\n")
            data = b""
            while chunk := sock.recv(65536):
                data += chunk
    finally:
        srv.shutdown()
        srv.server_close()
    head, _, body = data.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 403 ") and data.count(b"HTTP/1.1 ") == 1, data
    assert json.loads(body) == {"error": "host 'evil.example' refused: the viewer answers loopback addresses only"}
