"""The output-folder layout (``formats.layout``): the ``iteration`` argument of the loaders, and which
``point_cloud/iteration_<N>`` folder is read."""

from __future__ import annotations

import numpy as np
import pytest

from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.layout import bitstreams_only, check_iteration, iteration_dir, iteration_dirs


@pytest.mark.parametrize("value", ["abc", -1, 2.5, True, "3.0", [3]])
def test_an_iteration_that_is_not_a_whole_number_is_refused_naming_it(tmp_path, value):
    with pytest.raises(InputValueError, match=r"^iteration must be a whole number >= 0"):
        check_iteration(value)
    (tmp_path / "point_cloud" / "iteration_7").mkdir(parents=True)
    with pytest.raises(InputValueError, match="iteration"):
        iteration_dir(tmp_path, value, family="Scaffold-GS")


def test_whole_numbers_are_taken():
    assert check_iteration(None) is None
    assert check_iteration(7) == 7 and check_iteration(np.int64(7)) == 7 and check_iteration(" 7 ") == 7


def test_the_newest_or_the_asked_iteration_folder_is_read(tmp_path):
    """Folders named exactly iteration_<N> count (not iteration_20_old, iteration_x, a file iteration_30):
    the largest N by default, else the one asked for; a missing one is named with those present."""
    pc = tmp_path / "point_cloud"
    for name in ("iteration_10", "iteration_7", "iteration_500", "iteration_20_old", "iteration_x", "old_iteration_40",
                 "iteration_99999.bak"):
        (pc / name).mkdir(parents=True)
    (pc / "iteration_30").write_text("")
    assert iteration_dirs(tmp_path) == {10: pc / "iteration_10", 7: pc / "iteration_7", 500: pc / "iteration_500"}
    assert iteration_dir(tmp_path, None, family="Fam") == pc / "iteration_500"
    assert iteration_dir(tmp_path, 7, family="Fam") == pc / "iteration_7"
    assert iteration_dir(tmp_path, "10", family="Fam") == pc / "iteration_10"
    with pytest.raises(FileFormatError, match=r"point_cloud: no 'iteration_8' folder \(present: \[7, 10, 500\]\)"):
        iteration_dir(tmp_path, 8, family="Fam")
    assert bitstreams_only(pc) == ""


def test_a_folder_without_iterations_is_refused_naming_a_compressed_model(tmp_path):
    with pytest.raises(FileFormatError, match=r"no 'point_cloud/iteration_<N>' folder\)$"):
        iteration_dir(tmp_path, None, family="Fam")
    (tmp_path / "bitstreams").mkdir()
    with pytest.raises(FileFormatError, match="not a Fam output directory.*bitstreams/ was found"):
        iteration_dir(tmp_path, None, family="Fam")
    (tmp_path / "point_cloud").mkdir()
    with pytest.raises(FileFormatError, match="point_cloud: no 'iteration_<N>' folder .*bitstreams/ was found"):
        iteration_dir(tmp_path, None, family="Fam")
