"""Adapter file: a header whose schedule endpoints cannot make a schedule is refused naming the file."""

from __future__ import annotations

import math

import pytest

from _adapter_files import rewrite, trained
from controlgs_adapter import ControlGS
from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.adapter import read_spec
from scaffold_standin import ScaffoldStandIn


@pytest.fixture
def saved(tmp_path):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = trained(model, modules=("lens", "display"))
    path = tmp_path / "scene.controlgs.safetensors"
    cgs.save(path)
    header = read_spec(path)
    cgs.unwrap()
    return model, path, header["schedules"]


@pytest.mark.parametrize("lo, hi", [(math.nan, 1.0), (0.0, math.inf), (-math.inf, 0.5), (0.25, 0.25)])
def test_schedule_endpoints_that_make_no_schedule_are_refused_naming_the_file(saved, lo, hi):
    model, path, schedules = saved
    rewrite(path, {"schedules": {**schedules, "display": {**schedules["display"], "lo": lo, "hi": hi}}})
    with pytest.raises(FileFormatError, match=rf"{path.name}: adapter header field schedules\.display: endpoints "
                                              rf"lo={lo!r}, hi={hi!r}"):
        ControlGS.load(path, model)
    assert ControlGS.attached(model) is None  # nothing was wrapped


def test_valid_endpoints_still_load(saved):
    model, path, schedules = saved
    rewrite(path, {"schedules": {**schedules, "display": {**schedules["display"], "lo": 0.1, "hi": 0.7}}})
    cgs = ControlGS.load(path, model)
    assert (cgs.schedules["display"].lo, cgs.schedules["display"].hi) == (0.1, 0.7)
    cgs.unwrap()
