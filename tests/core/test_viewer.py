"""Tests of ``controlgs_adapter.viewer``."""

from __future__ import annotations

from typing import Any

import pytest
from helpers.adapters import random_adapter

from controlgs_adapter.viewer import OPTICS_MODES, STAGES, ViewerSession, ViewState

SIZE = 16


# ---------------------------------------------------------------- the session
@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Any:
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene, render_planes

    scene = load_builtin_scene("ar", SIZE, views=4, test_every=4, samples=1)
    model = load_builtin_backbone("ar")
    d = tmp_path_factory.mktemp("viewer-sweep")
    adapters = {"controlgs": random_adapter(model, d / "a.controlgs.safetensors", 3),
                "blind": random_adapter(model, d / "b.controlgs.safetensors", 3, state_blind=True),
                "fov": random_adapter(model, d / "f.controlgs.safetensors", 3, modules=("foveation", "display"))}
    session = ViewerSession(model, scene.views("test"), adapters, name="tiny",
                            truth=lambda cam: render_planes(scene.planes, cam, samples=1)[0].float())
    return session, scene


def test_session_info(small: Any) -> None:
    session, _ = small
    info = session.info()
    assert info["name"] == "tiny" and info["views"] == [f"test view 0 ({SIZE}x{SIZE})"]
    assert [m["name"] for m in info["methods"]] == ["no_ss", "ss", "controlgs", "blind", "fov"]
    assert info["methods"][3] == {"name": "blind", "label": "blind"}  # no label of its own: the name
    assert info["stages"] == list(STAGES) and info["optics_modes"] == list(OPTICS_MODES)
    assert info["defaults"] == ViewState().to_json() and info["diff_gain"] == 2.0
    assert info["ranges"] == {"downsample": (1.0, 8.0), "power_saving": (0.0, 0.8), "azimuth": (-180.0, 180.0),
                              "elevation": (-80.0, 80.0)}
    assert info["orbit_truth"] is True and info["device"] == "cpu"
    assert info["extra_metrics"] == list(session.extra_metrics)
