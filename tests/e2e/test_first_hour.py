"""A new user's first hour, through the command line only: from a dataset folder (a tiny capture in each
format: COLMAP with sparse points, Blender, instant-ngp) to a backbone (`controlgs backbone train`), an
adapter (`controlgs train`), a report (`controlgs eval`) and the viewer (`controlgs view`, its server
answering one render request on a free port instead of serving until interrupted)."""

from __future__ import annotations

import http.client
import json
import threading

import pytest

pytest.importorskip("skimage")  # the capture is the built-in scene's
pytest.importorskip("matplotlib")  # the report's plots

from helpers.capture import FORMATS, write_capture

from controlgs_adapter.backends.model_dir import detect_family
from controlgs_adapter.cli import main
from controlgs_adapter.viewer.server import ViewerServer

# tiny and cheap: 24 px images, a short backbone, a 3-iteration adapter through the two cheap stages
BACKBONE = ["--iterations", "30", "--max-anchors", "150", "--no-progress"]
ADAPTER = ["--iterations", "3", "--no-ablations", "--effects", "resample,display", "--checkpoint-every", "0",
           "--no-progress"]


def _answer_one_render(monkeypatch, answers: list[dict]) -> None:
    """``serve_forever`` serves in a thread, posts one render request for view 0, keeps the answer and
    shuts the server down (the command then returns as after Ctrl-C)."""
    serve = ViewerServer.serve_forever

    def once(self: ViewerServer, poll_interval: float = 0.5) -> None:
        thread = threading.Thread(target=serve, args=(self,), daemon=True)
        thread.start()
        try:
            conn = http.client.HTTPConnection(*self.server_address[:2], timeout=120)
            conn.request("POST", "/api/render", body=json.dumps({"view": 0}), headers={"Content-Type": "application/json"})
            resp = conn.getresponse()
            answers.append({"status": resp.status, **json.loads(resp.read())})
            conn.close()
        finally:
            self.shutdown()
            thread.join()

    monkeypatch.setattr(ViewerServer, "serve_forever", once)


@pytest.mark.parametrize("fmt", FORMATS)
def test_from_a_dataset_folder_to_a_report_and_the_viewer(tmp_path, capsys, monkeypatch, fmt):
    data = write_capture(tmp_path / "data", fmt)
    model, run, report = tmp_path / "model", tmp_path / "run", tmp_path / "report"

    assert main(["backbone", "train", "--data", str(data), "--out", str(model), *BACKBONE]) == 0
    out = capsys.readouterr().out
    info = json.loads((model / "build.json").read_text())
    assert info["format"] == fmt and info["anchors_from"] == ("points" if fmt == "colmap" else "grid")
    assert 0 < info["anchors"] <= 150 and info["test_views"] == 1 and info["test_psnr_mean"] > 10.0
    assert f"PSNR {info['test_psnr_mean']:.2f} dB, SSIM {info['test_ssim_mean']:.4f}" in out
    assert f"next: controlgs train --model {model} --data {data} --out RUN" in out
    assert detect_family(model) == "scaffold_gs"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "model"]  # no temporary folder left beside it

    assert main(["train", "--model", str(model), "--data", str(data), "--out", str(run), *ADAPTER]) == 0
    assert (run / "controlgs.controlgs.safetensors").is_file()
    assert json.loads((run / "run.json").read_text())["model"] == str(model.resolve())

    assert main(["eval", "--run", str(run), "--out", str(report), "--no-progress"]) == 0
    results = json.loads((report / "results.json").read_text())
    assert set(results["methods"]) == {"no_ss", "ss", "ideal", "controlgs"}
    assert (report / "report.md").is_file() and (report / "heatmap.png").stat().st_size > 0

    answers: list[dict] = []
    _answer_one_render(monkeypatch, answers)
    assert main(["view", "--run", str(run), "--port", "0"]) == 0
    assert "serving on http://127.0.0.1:" in capsys.readouterr().out
    (answer,) = answers
    assert answer["status"] == 200, answer
    assert [m["name"] for m in answer["methods"]] == ["no_ss", "ss", "controlgs"]
    assert answer["size"] == [24, 24] and all(m["eye"] for m in answer["methods"])
