"""The contract of a backbone family: its loader and its backend, checked on a small trained output folder.

Every built-in family passes it (``tests/backends/test_family_contract.py``); a plug-in family can reuse it
in its own tests::

    from helpers.family_contract import Family, check_family

    def test_my_family_meets_the_contract(tmp_path):
        check_family(Family("my_family", write=write_my_folder, load=load_my_folder), tmp_path)

What is checked (each check is also a function of its own):

* :func:`check_loads`: the folder loads, the family's backend is the one :func:`plugins.select_backend`
  picks for the model, the model renders through the render protocol by itself;
* :func:`decoder_rows`: decoding a view feeds every target decoder ``rows_per_anchor`` rows per anchor of
  ``backend.rows_for(model, mask)``, in that order;
* :func:`check_wrap_identity_and_rows` (``helpers.family_checks``): ``ControlGS.wrap`` attaches to every
  target decoder; outputs are bit-identical to the backbone at zero conditions, outside ``conditioned`` and
  after ``unwrap``; one anchor's condition reaches exactly its rows; the saved adapter loads onto a fresh
  copy of the backbone and gives the same outputs;
* :func:`check_zero_strength`: an adapter with random parameters leaves the outputs bit-identical at a
  run-time state whose strengths are all zero;
* :func:`check_refusals`: a truncated point cloud, a truncated weights file, a missing folder and a folder
  of another family are refused with ``FileFormatError`` naming the file or folder.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest
import torch
from helpers.adapter_files import trained
from helpers.family_checks import check_wrap_identity_and_rows, make_camera, outputs

from controlgs_adapter import Camera, RuntimeState, plugins
from controlgs_adapter.backend import get_attr_path
from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.rendering.protocol import ModelRenderer, renderer_for

#: every built-in schedule is zero here: no resampling (d = 1), no power saving (rho = 0)
ZERO = RuntimeState(downsample=1.0, power_saving=0.0)


@dataclass(frozen=True)
class Family:
    """One family and layout under test.

    Attributes:
        backend: the name its backend is registered under.
        write: ``write(root)`` writes a small trained output folder at ``root`` (a path that does not
            exist yet) and returns the file holding the decoder weights.
        load: the family's loader, ``load(root) -> model``.
        foreign: ``foreign(root)`` writes, at ``root``, the output folder of another family, which
            ``load`` refuses.
        camera: the view decoded by the checks (it should see at least two anchors).
    """

    backend: str
    write: Callable[[Path], Path]
    load: Callable[[Path], Any]
    foreign: Callable[[Path], Any]
    camera: Camera = field(default_factory=make_camera)


def check_family(family: Family, tmp_path: Path) -> None:
    """Every check of the contract on a folder written under ``tmp_path``."""
    root = tmp_path / "model"
    family.write(root)
    model = check_loads(family, root)
    ids, inputs = decoder_rows(family, model)
    check_wrap_identity_and_rows(model, inputs, ids, family.backend, backend_of(model).rows_per_anchor(model),
                                 tmp_path, lambda: family.load(root))
    check_zero_strength(family, model)
    check_refusals(family, tmp_path / "refusals")


def backend_of(model: Any) -> Any:
    """The backend :func:`ControlGS.wrap` picks for ``model``."""
    return plugins.select_backend(model, None)


def check_loads(family: Family, root: Path) -> Any:
    """The folder at ``root`` loads, in eval mode, recognised by the family's backend, with anchors and a
    renderer of its own. Returns the model."""
    model = family.load(root)
    backend = backend_of(model)
    assert backend.name == family.backend
    assert not getattr(model, "training", False)
    assert backend.num_anchors(model) > 0
    assert backend.default_targets(model)
    assert type(renderer_for(model)) is ModelRenderer
    return model


@contextlib.contextmanager
def recorded(model: Any, paths: list[str]) -> Iterator[dict[str, list[torch.Tensor]]]:
    """Record the inputs of the decoders at ``paths`` (looked up now: wrapping may replace them) while
    the block runs: ``{path: [input of each call]}``."""
    seen: dict[str, list[torch.Tensor]] = {p: [] for p in paths}
    handles = [get_attr_path(model, p).register_forward_pre_hook(
        lambda module, args, p=p: seen[p].append(args[0].detach().clone())) for p in paths]
    try:
        yield seen
    finally:
        for h in handles:
            h.remove()


def decoder_rows(family: Family, model: Any) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Decode ``family.camera`` for every other anchor it sees and check the decoder rows against the
    backend: each target decoder is called once, with ``rows_per_anchor`` rows for each anchor of
    ``backend.rows_for(model, mask)``. Returns those anchor ids and ``{decoder: its input rows}``."""
    backend = backend_of(model)
    targets = backend.default_targets(model)
    visible = model.visible_anchors(family.camera)
    mask = visible.clone()
    mask[visible.nonzero().squeeze(1)[1::2]] = False  # a proper subset: row i is not anchor i
    ids = backend.rows_for(model, mask)
    assert len(ids) >= 2, "the camera must see at least 3 anchors"
    assert torch.equal(ids, mask.nonzero().squeeze(1))
    with recorded(model, targets) as seen, torch.no_grad():
        model.decode(family.camera, mask)
    k = backend.rows_per_anchor(model)
    for p, calls in seen.items():
        assert len(calls) == 1, (p, len(calls))
        assert calls[0].shape[0] == len(ids) * k, (p, calls[0].shape, len(ids), k)
    return ids, {p: calls[0] for p, calls in seen.items()}


def check_zero_strength(family: Family, model: Any) -> None:
    """With random adapter parameters, a run-time state whose strengths are all zero leaves every target
    decoder and the decoded Gaussians bit-identical to the backbone's."""
    mask = model.visible_anchors(family.camera)
    with torch.no_grad():
        want = model.decode(family.camera, mask)
    cgs = trained(model, modules=("resample", "display"))
    try:
        inputs = {p: torch.randn(3 * backend_of(model).rows_per_anchor(model), cgs.targets[i].in_features,
                                 generator=torch.Generator().manual_seed(i))
                  for i, p in enumerate(t.decoder for t in cgs.targets)}
        before = outputs(model, inputs)
        with cgs.conditioned(ZERO, family.camera, torch.tensor([0, 1, 2])):
            for p, y in outputs(model, inputs).items():
                assert torch.equal(y, before[p]), p
        with cgs.conditioned(ZERO, family.camera, mask), torch.no_grad():
            got = model.decode(family.camera, mask)
        for name in ("means", "scales", "rotations", "opacities", "colors", "anchor_of", "offset_of"):
            assert torch.equal(getattr(got, name), getattr(want, name)), name
    finally:
        cgs.unwrap()


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def check_refusals(family: Family, tmp_path: Path) -> None:
    """A truncated ``point_cloud.ply``, a truncated weights file, a missing folder and another family's
    folder are each refused with ``FileFormatError`` naming the file (or folder)."""
    root = tmp_path / "ply"
    family.write(root)
    (ply,) = root.glob("point_cloud/iteration_*/point_cloud.ply")
    _truncate(ply)
    with pytest.raises(FileFormatError) as e:
        family.load(root)
    assert "point_cloud.ply" in str(e.value), str(e.value)
    root = tmp_path / "weights"
    weights = family.write(root)
    _truncate(weights)
    with pytest.raises(FileFormatError) as e:
        family.load(root)
    assert weights.name in str(e.value), str(e.value)
    with pytest.raises(FileFormatError, match="nowhere"):
        family.load(tmp_path / "nowhere")
    other = tmp_path / "other"
    family.foreign(other)
    with pytest.raises(FileFormatError) as e:
        family.load(other)
    assert str(other) in str(e.value), str(e.value)
