"""Output-folder layout: the iteration argument of the loaders."""

from __future__ import annotations

import numpy as np
import pytest

from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.layout import check_iteration, iteration_dir


@pytest.mark.parametrize("value", ["abc", -1, 2.5, True, "3.0", [3]])
def test_an_iteration_that_is_not_a_whole_number_is_refused_naming_it(tmp_path, value):
    with pytest.raises(InputValueError, match=r"^iteration must be a whole number >= 0"):
        check_iteration(value)
    (tmp_path / "point_cloud" / "iteration_7").mkdir(parents=True)
    with pytest.raises(InputValueError, match="iteration"):
        iteration_dir(tmp_path, value, family="Scaffold-GS")


def test_whole_numbers_are_taken(tmp_path):
    assert check_iteration(None) is None
    assert check_iteration(7) == 7 and check_iteration(np.int64(7)) == 7 and check_iteration(" 7 ") == 7
    (tmp_path / "point_cloud" / "iteration_7").mkdir(parents=True)
    assert iteration_dir(tmp_path, "7", family="Scaffold-GS").name == "iteration_7"
    with pytest.raises(FileFormatError, match=r"no 'iteration_8' folder \(present: \[7\]\)"):
        iteration_dir(tmp_path, 8, family="Scaffold-GS")
