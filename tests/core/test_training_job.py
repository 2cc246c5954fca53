"""Progress of a job of several trainings (ControlGS and ablations, times seeds): each bar names its
method, seed and place in the job, and the job's estimated time left."""

from __future__ import annotations

import re

import pytest

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.training import TrainingJob


def test_titles_count_the_trainings_and_the_estimate_covers_the_whole_job():
    job = TrainingJob(4, 10)
    assert job.remaining() is None and job.remaining_text() == "?"  # nothing ran yet
    assert job.start("training ControlGS, seed 0") == "[1/4] training ControlGS, seed 0"
    for _ in range(5):
        job.step(2.0)
    # 5 of 40 iterations done at 2 s each: 35 left, about 70 s
    assert job.remaining() == pytest.approx(70.0) and job.remaining_text() == "~1m10s"
    for _ in range(5):
        job.step(2.0)
    assert job.start("training w/o Lens, seed 0", already=4) == "[2/4] training w/o Lens, seed 0"
    # a resumed checkpoint's 4 iterations count as done and are not timed: 40 - 14 = 26 left at 2 s
    assert job.remaining() == pytest.approx(52.0)
    job.start("c")
    job.start("d")
    assert job.start("beyond") == "[4/4] beyond"  # never counts past N
    assert TrainingJob(1, 1).remaining_text() == "?"
    for bad in ((0, 10), (2, -1)):
        with pytest.raises(InputValueError):
            TrainingJob(*bad)


def test_the_duration_reads_in_seconds_minutes_and_hours():
    job = TrainingJob(1, 3601)
    job.step(1.0)
    assert job.remaining_text() == "~1h00m"
    job = TrainingJob(1, 46)
    job.step(1.0)
    assert job.remaining_text() == "~45s"


def test_train_with_seeds_and_ablations_names_each_bar(tmp_path, capsys):
    pytest.importorskip("skimage")  # the built-in scene
    from controlgs_adapter.cli import main

    assert main(["train", "--out", str(tmp_path / "run"), "--resolution", "16", "--iterations", "2", "--seeds", "2",
                 "--ablation", "wo_lens", "--effects", "resample,display", "--checkpoint-every", "0"]) == 0
    err = capsys.readouterr().err
    titles = sorted(set(re.findall(r"\[\d/\d\] training [^:]+, seed \d", err)))
    assert titles == ["[1/4] training ControlGS, seed 0", "[2/4] training w/o Lens, seed 0",
                      "[3/4] training ControlGS, seed 1", "[4/4] training w/o Lens, seed 1"]
    assert re.search(r"total left=~\d+s", err)
    assert "training ControlGS:" not in err  # no bar without its method, seed and place
