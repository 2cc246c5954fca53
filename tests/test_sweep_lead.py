"""Tests for misses of the library-wide fresh mutation samples (docs/testing.md, automatic sweep)."""

from __future__ import annotations

import tempfile

import pytest
import torch

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_io import save_scaffold_dir
from controlgs_adapter.cli import main
from controlgs_adapter.datasets.base import Frame, SceneData
from controlgs_adapter.datasets.sanity import check_scene
from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.state import Camera


def test_save_stages_the_folder_beside_its_destination(tmp_path, monkeypatch):
    """The iteration folder is written under a temporary name next to where it ends (one filesystem, so
    the final rename is atomic), never in the system's temp folder: pointing that at a missing path
    changes nothing."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "no-such-folder"))
    model = NeuralGaussianModel(4, feat_dim=8, n_offsets=2).eval()
    save_scaffold_dir(model, tmp_path / "out", 7)
    assert (tmp_path / "out" / "point_cloud" / "iteration_7" / "point_cloud.ply").is_file()
    assert sorted(p.name for p in (tmp_path / "out" / "point_cloud").iterdir()) == ["iteration_7"]


def _frames(sizes: list[tuple[int, int]]) -> list[Frame]:
    k = torch.tensor([[4.0, 0.0, 4.0], [0.0, 4.0, 3.0], [0.0, 0.0, 1.0]])
    return [Frame(f"v{i}", Camera(torch.eye(4), k, 8, 6), torch.zeros(3, h, w)) for i, (w, h) in enumerate(sizes)]


@pytest.mark.parametrize("n_bad, tail", [(5, "v4 is 9x6, its camera 8x6"), (6, "v4 is 9x6, its camera 8x6; ...")])
def test_size_check_names_five_images_then_ellipsis(n_bad, tail):
    """At most five mismatched images are named; '; ...' follows only when there are more."""
    data = SceneData({"train": _frames([(9, 6)] * n_bad + [(8, 6)])}, source="src")
    with pytest.raises(FileFormatError) as e:
        check_scene(data)
    msg = str(e.value)
    assert msg.startswith(f"{n_bad} of {n_bad + 1} images do not match their camera's size: v0 is 9x6")
    assert msg.endswith(tail) and msg.count(" is 9x6") == 5


def test_scene_help_names_its_actions(capsys):
    with pytest.raises(SystemExit) as e:
        main(["scene", "--help"])
    assert e.value.code == 0
    usage = capsys.readouterr().out.split("\n\n")[0]
    assert usage.split() == ["usage:", "controlgs", "scene", "[-h]", "ACTION", "..."]


def test_yaml_scalars_survive_bytes_that_are_not_utf8(tmp_path):
    """Octree-AnyGS configs are read as text with undecodable bytes replaced (a Latin-1 comment or
    path), not refused with a UnicodeDecodeError."""
    from controlgs_adapter.formats.backbone import read_yaml_scalars

    path = tmp_path / "config.yaml"
    path.write_bytes(b"# caf\xe9 scene\nmodel:\n  voxel_size: 0.01  # m\xe9tres\n  name: sc\xe8ne\n")
    assert read_yaml_scalars(path) == {"voxel_size": [0.01], "name": ["sc\ufffdne"]}
