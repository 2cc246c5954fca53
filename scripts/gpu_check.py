"""The device check of a GPU machine, in one run that fits ten minutes (``scripts/gpu_check.sh`` installs the
carried wheels and runs it; docs/how-to/gpu.md).

Steps, each timed and recorded in one results JSON (written again after every step, so a run cut short
still reports what it did): the CUDA environment; gsplat's CUDA kernels built (JIT) and a render with them;
the suite's CUDA tests (``pytest``, none of them skipped); ``controlgs train`` + ``eval`` on the built-in
scene with ``--device cpu`` (the reference), ``--device cuda --rasterizer torch`` (checked against it within
:data:`TOLERANCES`) and ``--device cuda`` with gsplat, each in this process so the script sees where the
parameters and the loss live and how much GPU memory was allocated; the same once under ``torchrun`` with
NCCL and world size 1 (the adapter equal to the single-process one); ``backbone train`` + ``train`` + ``eval``
on an own scene (a COLMAP capture of the built-in scene, written here); the step benchmark's GPU rows.
A table of the steps prints last.

``--dry-run`` (no GPU needed): says which carried wheels are missing (one line each), checks every command
line parses (argparse, nothing run) and runs the CPU parts at the tiniest sizes.

Usage: ``python scripts/gpu_check.py [--dry-run] [--wheels DIR] [--out DIR] [--budget SECONDS]``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

#: what the GPU machine installs from the carried wheels (their dependencies are checked from their metadata)
REQUIREMENTS = ["torch==2.13.0", "gsplat>=1.4", "jaxtyping", "rich", "ninja", "numpy>=1.24", "pluggy>=1.3",
                "safetensors>=0.4", "colour-science>=0.4.4", "tqdm>=4.60", "pillow>=9", "flip-evaluator>=1.7",
                "scikit-image>=0.21", "matplotlib>=3.7", "pytest>=7", "hypothesis>=6.80", "setuptools>=68", "wheel",
                "packaging"]

#: the target of the carried wheels (pip download --platform ... --python-version 3.11)
TARGET = {"python_version": "3.11", "python_full_version": "3.11.0", "sys_platform": "linux", "platform_system": "Linux",
          "platform_machine": "x86_64", "os_name": "posix", "implementation_name": "cpython",
          "platform_python_implementation": "CPython", "extra": ""}

#: the suite's CUDA tests: files and the -k expression that selects them (they skip without a GPU; here none may)
CUDA_TEST_FILES = ["tests/rendering/test_rasterizers.py", "tests/downstream/optics/test_operators.py",
                   "tests/downstream/test_pipeline.py", "tests/core/test_training.py", "tests/commands/test_train.py",
                   "tests/downstream/test_stage_contract.py"]
CUDA_TEST_SELECT = "cuda or stage_contract"

#: CPU vs CUDA agreement, the same seed, settings and (torch) rasterizer: float32 kernels differ in rounding,
#: so the first training loss agrees closely and the evaluation after a few steps a little less
TOLERANCES = {
    "first_loss_rel": 1e-4,         # |loss_cuda - loss_cpu| / loss_cpu of step 1 (same view, same state)
    "losses_rel": 1e-2,             # every later step's loss
    "psnr_db": 0.05,                # every cell of every method's PSNR grid, CUDA (torch rasterizer) vs CPU
    "ssim": 1e-3,                   # likewise SSIM
    "psnr_db_gsplat": 0.5,          # each method's mean PSNR, CUDA with gsplat vs CPU (another rasterizer)
    "nccl_adapter_abs": 1e-4,       # torchrun world size 1 (NCCL) vs one process: every adapter tensor
}

#: the small settings of the built-in-scene runs: (resolution, iterations)
SMALL = {"run": (32, 8), "dry": (16, 2)}


# ----------------------------------------------------------------------------- the carried wheels
def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def wheel_index(folder: Path) -> dict[str, list[tuple[str, Path]]]:
    """``{normalised name: [(version, wheel file), ...]}`` of the ``.whl`` files in ``folder``."""
    index: dict[str, list[tuple[str, Path]]] = {}
    for f in sorted(folder.glob("*.whl")) if folder.is_dir() else []:
        name, version = f.name.split("-")[:2]
        index.setdefault(_norm(name), []).append((version, f))
    return index


def _requires(wheel: Path) -> list[str]:
    """The ``Requires-Dist`` lines of a wheel's METADATA."""
    with zipfile.ZipFile(wheel) as z:
        meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        text = z.read(meta).decode("utf-8", "replace")
    return [line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("Requires-Dist:")]


def missing_wheels(folder: Path, requirements: list[str] = REQUIREMENTS) -> list[str]:
    """One line per requirement (and dependency of a carried wheel, for Linux x86_64 Python 3.11) that no
    wheel in ``folder`` satisfies; empty when everything installs offline."""
    from packaging.requirements import Requirement
    from packaging.version import InvalidVersion, Version

    index, missing, seen = wheel_index(folder), [], set()
    todo = [(r, "requested") for r in requirements]
    while todo:
        text, why = todo.pop()
        req = Requirement(text)
        if req.marker is not None and not req.marker.evaluate(TARGET):
            continue
        key = (_norm(req.name), str(req.specifier))
        if key in seen:
            continue
        seen.add(key)
        found = []
        for version, wheel in index.get(_norm(req.name), []):
            with contextlib.suppress(InvalidVersion):
                if req.specifier.contains(Version(version.replace("%2B", "+")), prereleases=True):
                    found.append(wheel)
        if not found:
            missing.append(f"missing wheel: {req.name}{req.specifier} ({why})")
            continue
        todo += [(r, f"needed by {found[-1].name}") for r in _requires(found[-1])]
    return sorted(missing)


# ----------------------------------------------------------------------------- the commands
def commands(work: Path, small: tuple[int, int], device: str) -> dict[str, list[str]]:
    """The ``controlgs`` command lines of the check (argv after ``controlgs``), by name, in run order;
    ``device``: the GPU run's device (``cuda``) or ``cpu`` for the dry run."""
    res, its = small
    common = ["--resolution", str(res), "--test-views", "1", "--no-progress"]
    train = ["train", "--iterations", str(its), "--no-ablations", "--checkpoint-every", "0", *common]
    cap, model = str(work / "capture"), str(work / "own-model")
    return {
        "train_cpu": [*train, "--out", str(work / "cpu"), "--device", "cpu", "--rasterizer", "torch"],
        "eval_cpu": ["eval", "--run", str(work / "cpu"), "--out", str(work / "cpu-report"), "--device", "cpu",
                     "--rasterizer", "torch", *common],
        "train_cuda_torch": [*train, "--out", str(work / "cuda-torch"), "--device", device, "--rasterizer", "torch"],
        "eval_cuda_torch": ["eval", "--run", str(work / "cuda-torch"), "--out", str(work / "cuda-torch-report"),
                            "--device", device, "--rasterizer", "torch", *common],
        "train_cuda_gsplat": [*train, "--out", str(work / "cuda-gsplat"), "--device", device, "--rasterizer",
                              "gsplat" if device != "cpu" else "auto"],
        "eval_cuda_gsplat": ["eval", "--run", str(work / "cuda-gsplat"), "--out", str(work / "cuda-gsplat-report"),
                             "--device", device, *common],
        "train_nccl": [*train, "--out", str(work / "nccl"), "--device", device, "--rasterizer", "torch",
                       "--dist-backend", "nccl" if device != "cpu" else "gloo"],
        "own_backbone": ["backbone", "train", "--data", cap, "--out", model, "--iterations", str(20 * its),
                         "--resolution", "24", "--device", device, "--no-progress"],
        "own_train": ["train", "--model", model, "--data", cap, "--out", str(work / "own"), "--iterations", str(its),
                      "--no-ablations", "--checkpoint-every", "0", "--resolution", "24", "--device", device, "--no-progress"],
        "own_eval": ["eval", "--run", str(work / "own"), "--out", str(work / "own-report"), "--device", device,
                     "--no-progress"],
    }


def torchrun_argv(argv: list[str]) -> list[str]:
    """``torchrun --standalone --nproc_per_node=1 -m controlgs_adapter.cli <argv>``, as torchrun's own arguments."""
    return ["--standalone", "--nproc_per_node=1", "-m", "controlgs_adapter.cli", *argv]


def bench_argv(out: Path, device: str) -> list[str]:
    """The step benchmark's rows: 10k anchors at 256 px, exact and distortion optics, both rasterizers."""
    return ["--device", device, "--anchors", "10000" if device != "cpu" else "300", "--sizes", "256" if device != "cpu" else "64",
            "--optics", "exact", "distortion", "--rasterizer", "torch", "gsplat", "--reps", "2" if device != "cpu" else "1",
            "--out", str(out)]


class _Parsed(BaseException):
    """Raised by the patched ``parse_args`` once the arguments parsed: nothing runs."""


def parses(main: Callable[[list[str]], Any], argv: list[str]) -> str | None:
    """None if ``main(argv)`` parses its arguments with argparse (stopped right there), else why not."""
    original = argparse.ArgumentParser.parse_args

    def parse(self: argparse.ArgumentParser, args: Any = None, namespace: Any = None) -> Any:
        original(self, args, namespace)
        raise _Parsed

    argparse.ArgumentParser.parse_args = parse  # type: ignore[assignment]
    try:
        with contextlib.redirect_stderr(sys.stdout):
            main(argv)
    except _Parsed:
        return None
    except SystemExit as e:
        return f"argparse refused it (exit {e.code})"
    finally:
        argparse.ArgumentParser.parse_args = original  # type: ignore[method-assign]
    return "no argument parsing seen"


def parse_problems(work: Path) -> list[str]:
    """One line per command line of the check that does not parse."""
    from torch.distributed.run import get_args_parser

    from controlgs_adapter.cli import main as controlgs

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_step  # type: ignore[import-not-found]

    problems = []
    for device in ("cpu", "cuda"):
        for name, argv in commands(work, SMALL["run"], device).items():
            why = parses(controlgs, argv)
            if why:
                problems.append(f"controlgs {' '.join(argv)}: {why}")
        why = parses(bench_step.main, bench_argv(work / "bench.md", device))
        if why:
            problems.append(f"bench_step.py: {why}")
    try:
        get_args_parser().parse_args(torchrun_argv(commands(work, SMALL["run"], "cuda")["train_nccl"]))
    except SystemExit:
        problems.append("torchrun: its arguments do not parse")
    problems += [f"CUDA test file missing: {f}" for f in CUDA_TEST_FILES if not (ROOT / f).is_file()]
    return problems


# ----------------------------------------------------------------------------- running
class Check:
    """The results JSON, written after every step, and the time left."""

    def __init__(self, out: Path, budget: float) -> None:
        self.out, self.deadline = out, time.monotonic() + budget
        self.results: dict[str, Any] = {"steps": {}, "tolerances": TOLERANCES}
        out.mkdir(parents=True, exist_ok=True)

    def left(self) -> float:
        return self.deadline - time.monotonic()

    def step(self, name: str, work: Callable[[dict[str, Any]], None], needs: float = 0.0) -> dict[str, Any]:
        """Run ``work(record)`` as step ``name`` and record it (ok, seconds, what it found, ``failures``);
        skipped when less than ``needs`` seconds are left. Returns the record."""
        rec: dict[str, Any] = {"ok": False, "failures": []}
        self.results["steps"][name] = rec
        t0 = time.monotonic()
        if self.left() < needs:
            rec.update(ok=None, detail=f"skipped: {self.left():.0f} s left, needs about {needs:.0f}")
        else:
            try:
                work(rec)
                rec["ok"] = not rec["failures"]
            except Exception as e:  # noqa: BLE001 - every step reports, the next one runs
                rec["error"] = f"{type(e).__name__}: {str(e)[-2000:]}"
        rec["seconds"] = round(time.monotonic() - t0, 1)
        self.save()
        result = "ok" if rec["ok"] else "skipped" if rec["ok"] is None else "FAILED"
        print(f"[{name}] {result} ({rec['seconds']} s) {'; '.join(rec['failures'])} {rec.get('error', '')}".rstrip(), flush=True)
        return rec

    def save(self) -> None:
        (self.out / "gpu_check.json").write_text(json.dumps(self.results, indent=1, default=str) + "\n")

    def run(self, cmd: list[str], log: str, limit: float | None = None) -> subprocess.CompletedProcess[str]:
        """Run ``cmd`` at the repository root within the time left, its output in ``<out>/<log>.log``."""
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=max(1.0, min(limit or 1e9, self.left())))
        (self.out / f"{log}.log").write_text(res.stdout + res.stderr)
        return res


def in_process(argv: list[str]) -> dict[str, Any]:
    """``controlgs <argv>`` in this process: its exit code, the devices of the adapter's parameters and of
    the loss at every training step, the losses, and the CUDA memory it allocated."""
    import torch

    from controlgs_adapter import training
    from controlgs_adapter.cli import main

    seen: dict[str, Any] = {"param_devices": set(), "loss_devices": set(), "losses": []}
    step, loss = training.Trainer.step, training.image_loss

    def recorded_step(self: Any, *a: Any, **k: Any) -> float:
        seen["param_devices"] |= {str(p.device) for p in self.cgs.trainable_parameters()}
        value = step(self, *a, **k)
        seen["losses"].append(value)
        return value

    def recorded_loss(*a: Any, **k: Any) -> Any:
        out = loss(*a, **k)
        seen["loss_devices"].add(str(out.device))
        return out

    cuda = torch.cuda.is_available()
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    before = torch.cuda.memory_allocated() if cuda else 0
    training.Trainer.step, training.image_loss = recorded_step, recorded_loss  # type: ignore[method-assign]
    try:
        code = main(argv)
    finally:
        training.Trainer.step, training.image_loss = step, loss  # type: ignore[method-assign]
    peak = torch.cuda.max_memory_allocated() - before if cuda else 0
    return {"exit": code, "param_devices": sorted(seen["param_devices"]), "loss_devices": sorted(seen["loss_devices"]),
            "losses": seen["losses"], "cuda_peak_mib": round(peak / 2**20, 1)}


def _grids(report: Path) -> dict[str, dict[str, list[float]]]:
    """``{method: {metric: flattened grid}}`` of an evaluation's results.json."""
    data = json.loads((report / "results.json").read_text())

    def flat(x: Any) -> list[float]:
        return [v for item in x for v in flat(item)] if isinstance(x, list) else [float(x)]

    return {m: {k: flat(v["grid"]) for k, v in metrics.items()} for m, metrics in data["methods"].items()}


def compare(ref: dict[str, Any], got: dict[str, Any], ref_report: Path, report: Path, *, cells: bool) -> list[str]:
    """What differs beyond :data:`TOLERANCES` between a CPU run (``ref``) and a CUDA run (``got``)."""
    bad = []
    a, b = ref["losses"], got["losses"]
    if len(a) != len(b) or not a:
        return [f"losses: {len(a)} CPU steps, {len(b)} CUDA steps"]
    if cells:
        if abs(b[0] - a[0]) > TOLERANCES["first_loss_rel"] * abs(a[0]):
            bad.append(f"first loss: CPU {a[0]:.6g}, CUDA {b[0]:.6g}")
        bad += [f"loss of step {i + 1}: CPU {x:.6g}, CUDA {y:.6g}" for i, (x, y) in enumerate(zip(a, b))
                if abs(y - x) > TOLERANCES["losses_rel"] * abs(x)]
    ga, gb = _grids(ref_report), _grids(report)
    for method, metrics in ga.items():
        if cells:
            for metric, tol in (("psnr", TOLERANCES["psnr_db"]), ("ssim", TOLERANCES["ssim"])):
                worst = max(abs(x - y) for x, y in zip(metrics[metric], gb[method][metric]))
                if not worst <= tol:
                    bad.append(f"{method} {metric}: cells differ by up to {worst:.3g} (tolerance {tol})")
        else:
            d = abs(sum(metrics["psnr"]) / len(metrics["psnr"]) - sum(gb[method]["psnr"]) / len(gb[method]["psnr"]))
            if not d <= TOLERANCES["psnr_db_gsplat"]:
                bad.append(f"{method} mean PSNR differs by {d:.3g} dB (tolerance {TOLERANCES['psnr_db_gsplat']})")
    return bad


def on_gpu(run: dict[str, Any]) -> list[str]:
    """Why a CUDA run did not run on the GPU (empty: it did)."""
    bad = []
    if run["exit"] != 0:
        bad.append(f"exit code {run['exit']}")
    if not run["param_devices"] or any(not d.startswith("cuda") for d in run["param_devices"]):
        bad.append(f"adapter parameters on {run['param_devices']}")
    if not run["loss_devices"] or any(not d.startswith("cuda") for d in run["loss_devices"]):
        bad.append(f"loss on {run['loss_devices']}")
    if not run["cuda_peak_mib"] > 0:
        bad.append("no CUDA memory allocated")
    return bad


def gpu_run(check: Check, wheels: Path) -> None:
    """Every step on the GPU (see the module's docstring)."""
    import torch

    work = check.out / "work"
    cmds = commands(work, SMALL["run"], "cuda")
    runs: dict[str, dict[str, Any]] = {}

    def environment(rec: dict[str, Any]) -> None:
        rec.update(torch=torch.__version__, cuda=torch.version.cuda, available=torch.cuda.is_available(),
                   missing_wheels=missing_wheels(wheels))
        if torch.cuda.is_available():
            rec["device"] = torch.cuda.get_device_name(0)
        else:
            rec["failures"].append("torch.cuda.is_available() is False")

    def gsplat_build(rec: dict[str, Any]) -> None:
        from controlgs_adapter import plugins

        reason = plugins.rasterizers()["gsplat"].obj.unavailable(torch.device("cuda"), torch.float32)
        if reason:
            rec["failures"].append(reason)
            return
        import gsplat

        dev = torch.device("cuda")
        k = torch.tensor([[[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]]], device=dev)
        out, _, _ = gsplat.rasterization(  # the first call compiles the kernels
            torch.tensor([[0.0, 0.0, 2.0]], device=dev), torch.tensor([[1.0, 0, 0, 0]], device=dev),
            torch.full((1, 3), 0.1, device=dev), torch.ones(1, device=dev), torch.ones(1, 3, device=dev),
            torch.eye(4, device=dev)[None], k, 16, 16)
        rec.update(version=gsplat.__version__, centre=float(out[0, 8, 8, 0]))
        if not rec["centre"] > 0:
            rec["failures"].append("a Gaussian in front of the camera rendered black")

    def cuda_tests(rec: dict[str, Any]) -> None:
        xml = check.out / "cuda-tests.xml"
        res = check.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", *CUDA_TEST_FILES,
                         "-k", CUDA_TEST_SELECT, "--junitxml", str(xml)], "cuda-tests", limit=240)
        skips = re.findall(r'<skipped [^>]*message="([^"]*)"', xml.read_text() if xml.exists() else "")
        rec.update(summary=(res.stdout.strip().splitlines() or [""])[-1], skipped=skips)
        rec["failures"] += ([f"pytest exit {res.returncode}"] if res.returncode else [])
        rec["failures"] += [f"skipped: {s}" for s in skips if re.search(r"GPU|CUDA|gsplat", s, re.I)]

    def train_eval(tag: str) -> Callable[[dict[str, Any]], None]:
        def work_(rec: dict[str, Any]) -> None:
            runs[tag] = train = in_process(cmds[f"train_{tag}"])
            evaluation = in_process(cmds[f"eval_{tag}"])
            rec.update(train=train, eval_exit=evaluation["exit"], eval_cuda_peak_mib=evaluation["cuda_peak_mib"])
            rec["failures"] += [f"eval exit {evaluation['exit']}"] if evaluation["exit"] else []
            if tag == "cpu":
                rec["failures"] += [f"train exit {train['exit']}"] if train["exit"] else []
                return
            rec["failures"] += on_gpu(train) + ([] if evaluation["cuda_peak_mib"] > 0 else ["eval: no CUDA memory allocated"])
            if "cpu" in runs and not rec["failures"]:
                rec["failures"] += compare(runs["cpu"], train, work / "cpu-report", work / f"{tag.replace('_', '-')}-report",
                                           cells=tag == "cuda_torch")
            if tag == "cuda_gsplat":
                rec["rasterizer"] = json.loads((work / "cuda-gsplat" / "run.json").read_text()).get("rasterizer")
                rec["failures"] += [] if "gsplat" in json.dumps(rec["rasterizer"]) else [f"rasterizer {rec['rasterizer']}"]
        return work_

    def nccl(rec: dict[str, Any]) -> None:
        res = check.run([sys.executable, "-m", "torch.distributed.run", *torchrun_argv(cmds["train_nccl"])], "nccl", limit=120)
        if res.returncode:
            rec["failures"].append(f"torchrun exit {res.returncode}")
            return
        rec["distributed"] = json.loads((work / "nccl" / "run.json").read_text()).get("distributed")
        rec["failures"] += adapter_difference(work / "cuda-torch", work / "nccl")

    def own_scene(rec: dict[str, Any]) -> None:
        sys.path.insert(0, str(ROOT / "tests"))
        from helpers.capture import write_capture  # type: ignore[import-not-found]

        write_capture(work / "capture", "colmap", size=24)
        res = check.run([sys.executable, "-m", "controlgs_adapter.cli", *cmds["own_backbone"]], "own-backbone", limit=120)
        if res.returncode:
            rec["failures"].append(f"backbone train exit {res.returncode}")
            return
        rec["train"] = train = in_process(cmds["own_train"])
        rec["failures"] += on_gpu(train)
        if train["exit"] == 0:
            rec["eval_exit"] = in_process(cmds["own_eval"])["exit"]
            rec["failures"] += [f"eval exit {rec['eval_exit']}"] if rec["eval_exit"] else []

    def bench(rec: dict[str, Any]) -> None:
        res = check.run([sys.executable, "benchmarks/bench_step.py", *bench_argv(check.out / "bench-step-gpu.md", "cuda")],
                        "bench-step", limit=180)
        rec["rows"] = [line for line in res.stdout.splitlines() if line.startswith("| cuda")]
        rec["failures"] += [f"exit {res.returncode}"] if res.returncode else ([] if rec["rows"] else ["no CUDA rows"])

    if not check.step("environment", environment)["ok"]:
        return
    check.step("gsplat_build", gsplat_build, needs=150)
    check.step("cuda_tests", cuda_tests, needs=60)
    for tag, needs in (("cpu", 60), ("cuda_torch", 40), ("cuda_gsplat", 40)):
        check.step(f"train_eval_{tag}", train_eval(tag), needs=needs)
    check.step("nccl_world_size_1", nccl, needs=40)
    check.step("own_scene", own_scene, needs=60)
    check.step("bench_step_gpu", bench, needs=60)


def adapter_difference(a: Path, b: Path) -> list[str]:
    """The adapter tensors of two runs that differ by more than the NCCL tolerance."""
    from safetensors.torch import load_file

    fa, fb = (load_file(str(next(p.glob("*.controlgs.safetensors")))) for p in (a, b))
    if fa.keys() != fb.keys():
        return [f"adapter tensors: {sorted(fa)} vs {sorted(fb)}"]
    tol = TOLERANCES["nccl_adapter_abs"]
    return [f"adapter {k}: differs by {float((fa[k].double() - fb[k].double()).abs().max()):.3g}" for k in fa
            if not float((fa[k].double() - fb[k].double()).abs().max()) <= tol]


def dry_run(check: Check, wheels: Path) -> None:
    """What runs without a GPU: the wheel list, the command lines, the CPU parts at the tiniest size."""
    work = check.out / "work"
    cmds = commands(work, SMALL["dry"], "cpu")

    def wheels_(rec: dict[str, Any]) -> None:  # reported, not failed: the wheels are downloaded where there is a network
        rec["missing"] = missing_wheels(wheels)
        print("\n".join(rec["missing"]) or f"every wheel is in {wheels}")
        if rec["missing"]:
            rec["detail"] = f"{len(rec['missing'])} wheels missing from {wheels}"

    def parse(rec: dict[str, Any]) -> None:
        rec["failures"] += parse_problems(work)

    def collect(rec: dict[str, Any]) -> None:
        res = check.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                         *CUDA_TEST_FILES, "-k", CUDA_TEST_SELECT], "cuda-tests-collect")
        rec["collected"] = sum(1 for line in res.stdout.splitlines() if "::" in line)
        rec["failures"] += [f"pytest exit {res.returncode}"] if res.returncode else []

    def train_eval(rec: dict[str, Any]) -> None:
        train, evaluation = in_process(cmds["train_cpu"]), in_process(cmds["eval_cpu"])
        rec.update(train=train, eval_exit=evaluation["exit"])
        if train["exit"] or evaluation["exit"] or not all(map(math.isfinite, train["losses"])):
            rec["failures"].append(f"train exit {train['exit']}, eval exit {evaluation['exit']}, losses {train['losses']}")

    def bench(rec: dict[str, Any]) -> None:
        res = check.run([sys.executable, "benchmarks/bench_step.py", *bench_argv(check.out / "bench-step-cpu.md", "cpu"),
                         "--threads", "1"], "bench-step-cpu")
        rec["rows"] = [line for line in res.stdout.splitlines() if line.startswith("| cpu")]
        rec["failures"] += [f"exit {res.returncode}"] if res.returncode else ([] if rec["rows"] else ["no CPU rows"])

    check.step("wheels", wheels_)
    check.step("commands_parse", parse)
    check.step("cuda_tests_collect", collect)
    check.step("train_eval_cpu", train_eval)
    check.step("bench_step_cpu", bench)


def table(results: dict[str, Any]) -> str:
    """The steps as a Markdown table: step, result, seconds, what failed."""
    lines = ["| step | result | s | notes |", "|---|---|---:|---|"]
    for name, rec in results["steps"].items():
        result = "ok" if rec.get("ok") else "skipped" if rec.get("ok") is None else "FAILED"
        notes = "; ".join([*rec["failures"], *[rec[k] for k in ("error", "detail") if k in rec]])
        lines.append(f"| {name} | {result} | {rec.get('seconds', 0)} | {notes[:160]} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--dry-run", action="store_true", help="no GPU: wheels, command lines, the CPU parts at the tiniest size")
    ap.add_argument("--wheels", type=Path, default=ROOT / "shared" / "wheels", help="the carried wheels (default shared/wheels)")
    ap.add_argument("--out", type=Path, default=Path(os.environ.get("OUT") or ROOT / "gpu-check"),
                    help="folder of gpu_check.json and the logs (default $OUT, else gpu-check/)")
    ap.add_argument("--budget", type=float, default=540.0, help="seconds for the whole check (default 540)")
    args = ap.parse_args(argv)
    check = Check(args.out, args.budget)
    check.results["mode"] = "dry-run" if args.dry_run else "gpu"
    (dry_run if args.dry_run else gpu_run)(check, args.wheels)
    check.results["ok"] = all(rec.get("ok") for rec in check.results["steps"].values())
    check.save()
    print(f"\nresults: {args.out / 'gpu_check.json'}\n")
    print(table(check.results))
    return 0 if check.results["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
