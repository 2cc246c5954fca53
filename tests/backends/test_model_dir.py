"""Every family's loader: non-finite decoder weights, malformed cfg_args values and a malformed
iteration argument are refused, naming the file and the tensor / key."""

from __future__ import annotations

import re

import pytest

from controlgs_adapter import plugins
from controlgs_adapter.backends.model_dir import detect_family, load_model_dir
from controlgs_adapter.errors import FileFormatError, InputValueError
from helpers.family_dirs import FAMILIES, poison_first_weight, write_family_dir

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # TorchScript decoders: the format under test
WITH_CFG = [f for f in FAMILIES if f != "compgs"]  # CompGS keeps no cfg_args


def _anchors(model, family: str) -> int:
    return plugins.backends()[family.removesuffix("_split")].obj.num_anchors(model)


@pytest.mark.parametrize("family", FAMILIES)
def test_the_written_folders_load(tmp_path, family):
    write_family_dir(family, tmp_path)
    assert detect_family(tmp_path) == family.removesuffix("_split")
    assert _anchors(load_model_dir(tmp_path, allow_unquantized=True), family) > 0


@pytest.mark.parametrize("family", [f for f in FAMILIES if f != "scaffold_gs_split"])
def test_a_nan_decoder_weight_is_refused_naming_file_and_tensor(tmp_path, family):
    weights = write_family_dir(family, tmp_path)
    tensor = poison_first_weight(weights)
    with pytest.raises(FileFormatError, match=rf"{re.escape(str(weights))}.*: tensor '{re.escape(tensor)}' holds 1 NaN/Inf"):
        load_model_dir(tmp_path, allow_unquantized=True)


def test_a_nan_bound_of_contextgs_is_refused(tmp_path):
    import torch

    ckpt = write_family_dir("contextgs", tmp_path)
    blob = torch.load(ckpt, weights_only=True)
    blob["bound"][1][0, 2] = float("nan")
    torch.save(blob, ckpt)
    with pytest.raises(FileFormatError, match=rf"{re.escape(str(ckpt))}: tensor 'bound.1' holds 1 NaN/Inf"):
        load_model_dir(tmp_path)


@pytest.mark.parametrize("family", WITH_CFG)
@pytest.mark.parametrize("key, value", [("voxel_size", "abc"), ("feat_dim", "abc"), ("n_offsets", 2.5),
                                        ("voxel_size", float("nan"))])
def test_a_malformed_cfg_args_value_is_refused_naming_file_and_key(tmp_path, family, key, value):
    write_family_dir(family, tmp_path, **{key: value})
    with pytest.raises(FileFormatError, match=rf"{re.escape(str(tmp_path / 'cfg_args'))}: {key}=.* must be"):
        load_model_dir(tmp_path, allow_unquantized=True)


@pytest.mark.parametrize("family", FAMILIES)
def test_a_malformed_iteration_argument_is_refused_naming_it(tmp_path, family):
    write_family_dir(family, tmp_path)
    for fam in (None, family.removesuffix("_split")):
        with pytest.raises(InputValueError, match=r"^iteration must be a whole number >= 0.*got 'abc'"):
            load_model_dir(tmp_path, family=fam, iteration="abc", allow_unquantized=True)
    assert _anchors(load_model_dir(tmp_path, iteration="100", allow_unquantized=True), family) > 0
