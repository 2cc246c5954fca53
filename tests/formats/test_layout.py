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


from controlgs_adapter.formats import layout


def test_iteration_dir_choices_and_refusals(tmp_path):
    with pytest.raises(FileFormatError, match=r"no 'point_cloud/iteration_<N>' folder\)$"):
        layout.iteration_dir(tmp_path, None, family="Fam")
    (tmp_path / "bitstreams").mkdir()
    with pytest.raises(FileFormatError, match="not a Fam output directory.*bitstreams/ was found"):
        layout.iteration_dir(tmp_path, None, family="Fam")
    pc = tmp_path / "point_cloud"
    pc.mkdir()
    with pytest.raises(FileFormatError, match="point_cloud: no 'iteration_<N>' folder .*bitstreams/ was found"):
        layout.iteration_dir(tmp_path, None, family="Fam")
    for n in (7, 30000, 500):
        (pc / f"iteration_{n}").mkdir()
    (pc / "iteration_99999.bak").mkdir()
    (pc / "iteration_123456").write_bytes(b"")  # a file, not a folder
    assert layout.iteration_dirs(tmp_path) == {7: pc / "iteration_7", 30000: pc / "iteration_30000", 500: pc / "iteration_500"}
    assert layout.iteration_dir(tmp_path, None, family="Fam") == pc / "iteration_30000"
    assert layout.iteration_dir(tmp_path, 7, family="Fam") == pc / "iteration_7"
    with pytest.raises(FileFormatError, match=r"point_cloud: no 'iteration_8' folder \(present: \[7, 500, 30000\]\)"):
        layout.iteration_dir(tmp_path, 8, family="Fam")
    assert layout.bitstreams_only(tmp_path / "point_cloud") == ""


def test_iteration_folders_are_named_exactly_iteration_n(tmp_path):
    """iteration_10 and iteration_7 count; iteration_20_old, iteration_x and a file iteration_30 do not."""
    from controlgs_adapter.formats.layout import iteration_dir, iteration_dirs

    pc = tmp_path / "point_cloud"
    for name in ("iteration_10", "iteration_7", "iteration_20_old", "iteration_x", "old_iteration_40"):
        (pc / name).mkdir(parents=True)
    (pc / "iteration_30").write_text("")
    assert iteration_dirs(tmp_path) == {10: pc / "iteration_10", 7: pc / "iteration_7"}
    assert iteration_dir(tmp_path, None, family="Scaffold-GS") == pc / "iteration_10"
    with pytest.raises(FileFormatError, match=r"no 'iteration_20' folder \(present: \[7, 10\]\)"):
        iteration_dir(tmp_path, 20, family="Scaffold-GS")
