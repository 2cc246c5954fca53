"""Up-front dataset checks: the warning about cameras that see little of the scene points at the caller."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.datasets import Frame, SceneData, check_scene
from controlgs_adapter.state import Camera


def _camera(turn: bool) -> Camera:
    """4 units from the origin, facing it; ``turn``: facing away (the origin at depth -4)."""
    w2c = torch.eye(4)
    if turn:  # half a turn about y
        w2c[0, 0] = w2c[2, 2] = -1.0
    w2c[2, 3] = -4.0 if turn else 4.0
    return Camera(w2c, torch.tensor([[10.0, 0, 4], [0, 10.0, 3], [0, 0, 1]]), 8, 6)


def test_the_blind_camera_warning_points_at_the_callers_line():
    frames = [Frame(f"v{i}", _camera(turn=(i == 2)), torch.zeros(3, 6, 8)) for i in range(3)]
    data = SceneData({"train": frames, "test": []}, source="three-views")
    with pytest.warns(RuntimeWarning, match=r"three-views: 1 of 3 cameras see almost none .*: v2$") as caught:
        report = check_scene(data, torch.zeros(5, 3))
    assert report["blind"] == ["v2"]
    assert caught[0].filename == __file__
