"""The GPU checks of a session that is lent a GPU machine, in one command (prints figures; asserts nothing).

``python -m pcrcg.benchmarks.gpu_check [--out DIR] [--copy-to DIR2] [--device cuda] [--steps 150]
[--eval-pairs 20] [--skip tests,model,run]`` runs, each in its own process, and writes ``DIR/gpu_check.md``
and ``DIR/gpu_check.json`` (the figures) beside every step's log (``--copy-to``: those files alone, again):

1. ``tests``: ``pytest -m gpu`` (the CUDA paths the CPU never takes: ``tests/test_gpu.py``);
2. ``model``: ``python -m pcrcg.benchmarks.model`` at ``profile=paper`` on the device, geometry only and with
   deep color (the Res50 UNet): seconds per training step and per inference, and peak GPU memory, on training
   pairs of the tiny generated data (160x120 frames; ~13k points a pair at the paper's 2.5 cm voxels, where a
   real 3DMatch pair has ~35k);
3. ``run``: the main job through a run's real stages on the device (Lightning's ``trainer=gpu``,
   ``runtime.device``) with the paper profile's networks (:func:`paper_sized_overrides`) on the tiny
   generated data: geometry-only Predator, then PCR-CG (deep, a scratch Res50 UNet, implicit
   projection), ``--steps`` training steps and ``--eval-pairs`` test pairs per benchmark each, without a
   store (``logger=none``): the runs' stage times (``timings.json``) and recalls.

``profile=paper`` as a whole needs the paper's data (640x480 rooms, ~24 min each to generate on a CPU) and
30 epochs: this is the smoke test that the issue asks of a lent GPU, sized to fit one call of the device tool
(about 8 minutes with the defaults, an estimate: it has never run on a GPU; each step stops at ``--timeout``).
What the machine lacks is carried: the device image has no Hydra or OmegaConf (wheels: ``--download-wheels
DIR`` here, where pip reaches the registries), and none of Open3D, MLflow or kornia is needed by these steps (a
run reads PLY fragments by NumPy and ``logger=none`` keeps no store). With ``--device cpu`` the same steps run
here (a rehearsal: ``--steps 2 --eval-pairs 2``).

On a session's lent machine (the device tool's ``run``; README "On a GPU, and on several")::

    echo /.whl/ >> .git/info/exclude                                   # here, once
    .venv/bin/python -m pcrcg.benchmarks.gpu_check --download-wheels .whl
    .venv/bin/python -m pcrcg.prepare data=synthmatch profile=tiny     # data/synthmatch-tiny, if not there
    # run, carry [".whl", "data/synthmatch-tiny"], timeout_s 600:
    python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site &&
      python3 -m pcrcg.benchmarks.gpu_check --out /tmp/gpu_check --copy-to $OUT
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Sequence

REPO = Path(__file__).resolve().parents[2]
STEPS = ("tests", "model", "run")
# what the device image lacks of a run's dependencies (the device tool's list of its packages); pure Python
WHEELS = ("hydra-core==1.3.8", "omegaconf==2.3.0", "antlr4-python3-runtime==4.9.3")


def paper_sized_overrides(color: bool) -> list[str]:
    """Overrides that give a run of another profile the paper profile's networks: the 3D model's sizes and,
    with ``color``, the 2D encoder's (``conf/profile/paper.yaml``, composed: one home for the sizes)."""
    from omegaconf import OmegaConf

    from pcrcg.config import load_run_config

    paper = OmegaConf.to_container(load_run_config(["profile=paper"]).profile, resolve=True)
    out = [f"profile.model.{k}={paper['model'][k]}"  # type: ignore[index]
           for k in ("voxel_size", "num_layers", "first_dim", "gnn_dim", "max_points", "circle_points")]
    if color:
        out += [f"profile.encoder2d.{k}={json.dumps(paper['encoder2d'][k]).replace(' ', '')}"  # type: ignore[index]
                for k in ("arch", "out_dim", "decoder_channels", "normalize", "output_scale")]
    return out


def run_commands(out: Path, device: str, steps: int, eval_pairs: int, data_root: Path) -> dict[str, list[str]]:
    """The two runs of step 3 (name -> argv): Predator and PCR-CG with the paper's networks on ``data_root``."""
    common = ["profile=tiny", f"data.root={data_root}", "logger=none", "runtime.report_on_end=false",
              "trainer.progress_bar=false", f"runtime.device={device}", f"profile.train.max_steps={steps}",
              f"eval.max_pairs={eval_pairs}", "runtime.reuse_checkpoints=false"]
    if device.startswith("cuda"):
        common.append("trainer=gpu")
    runs = {"predator": ["features=none", *paper_sized_overrides(False)],
            "pcrcg": ["features=deep", "projection=implicit", "encoder2d=scratch", *paper_sized_overrides(True)]}
    return {name: [sys.executable, "-m", "pcrcg.run", *common, *extra, f"hydra.run.dir={out / ('run-' + name)}",
                   f"paths.checkpoints={out / ('ck-' + name)}"] for name, extra in runs.items()}


def _call(argv: Sequence[str], log: Path, timeout: float) -> dict[str, Any]:
    """Run ``argv`` in the repository, its output into ``log``: return code, wall seconds, the output's tail."""
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "PYTHONUNBUFFERED": "1"}
    try:
        res = subprocess.run(list(argv), cwd=REPO, capture_output=True, text=True, timeout=timeout, env=env)
        rc, text = res.returncode, res.stdout + res.stderr
    except subprocess.TimeoutExpired as e:  # its captured output is bytes whatever text= says
        text = "".join(x.decode(errors="replace") if isinstance(x, bytes) else x for x in (e.stdout, e.stderr) if x)
        rc, text = 124, f"{text}\n[gpu_check] timed out after {timeout:.0f} s"
    log.write_text(text)
    return {"rc": rc, "seconds": round(time.perf_counter() - t0, 1), "log": log.name, "tail": text[-1500:]}


def _environment() -> dict[str, Any]:
    import torch

    env: dict[str, Any] = {"python": sys.version.split()[0], "torch": torch.__version__,
                           "cuda": torch.cuda.is_available()}
    if env["cuda"]:
        p = torch.cuda.get_device_properties(0)
        env.update(gpu=p.name, gpu_memory_gb=round(p.total_memory / 2**30, 1), cuda_version=torch.version.cuda)
    return env


def _save(result: dict[str, Any], out: Path, copy_to: Path | None) -> None:
    """``gpu_check.json`` and ``.md`` into ``out`` and, with the steps' logs, into ``copy_to``: after every step,
    so that a call stopped at its time limit still brings back the steps that ended."""
    import shutil

    (out / "gpu_check.json").write_text(json.dumps(result, indent=1, default=str))
    (out / "gpu_check.md").write_text(summary(result))
    if copy_to is not None:
        copy_to.mkdir(parents=True, exist_ok=True)
        for f in [out / "gpu_check.json", out / "gpu_check.md", *sorted(out.glob("*.log"))]:
            shutil.copy2(f, copy_to / f.name)


def check(out: Path, device: str = "cuda", steps: int = 150, eval_pairs: int = 20, skip: Sequence[str] = (),
          data_root: Path | None = None, timeout: float = 200.0, copy_to: Path | None = None) -> dict[str, Any]:
    """Run the checks (module docstring) into ``out``; returns the figures written to ``gpu_check.json``."""
    out.mkdir(parents=True, exist_ok=True)
    data_root = data_root or REPO / "data" / "synthmatch-tiny"
    result: dict[str, Any] = {"environment": _environment(), "device": device, "steps": steps,
                              "eval_pairs": eval_pairs}
    py = sys.executable
    if "tests" not in skip:
        result["tests"] = _call([py, "-m", "pytest", "-q", "-m", "gpu", "-n", "0", "-p", "no:cacheprovider",
                                 "tests/test_gpu.py"], out / "tests.log", timeout)
        _save(result, out, copy_to)
    missing = None if (data_root / "manifest.json").is_file() else {
        "error": f"{data_root}: no data set (python -m pcrcg.prepare data=synthmatch profile=tiny where Open3D is, "
                 "then carry it)"}
    if "model" not in skip:
        result["model"] = missing or {}
        for color in () if missing else ("none", "deep"):
            r = _call([py, "-m", "pcrcg.benchmarks.model", "profiles=[paper]", "models=[predator]", f"device={device}",
                       f"color={color}", "compare=false", "pairs=4", "reps=3", "threads=4", f"root={data_root}"],
                      out / f"model-{color}.log", timeout)
            result["model"][color] = r
            _save(result, out, copy_to)
    if "run" not in skip:
        result["run"] = missing or {}
        if not missing:
            for name, argv in run_commands(out, device, steps, eval_pairs, data_root).items():
                r = _call(argv, out / f"run-{name}.log", timeout)
                folder = out / f"run-{name}"
                for f in ("timings.json", "metrics.json"):
                    if (folder / f).is_file():
                        data = json.loads((folder / f).read_text())
                        r[f.split(".")[0]] = data if f == "timings.json" else {
                            k: v for k, v in data.get("metrics", {}).items() if "/rr_" in k or "/fmr_" in k}
                result["run"][name] = r
                _save(result, out, copy_to)
    _save(result, out, copy_to)
    return result


def summary(result: dict[str, Any]) -> str:
    """The figures of :func:`check` as Markdown (what the session's note quotes)."""
    env = result["environment"]
    lines = [f"# GPU check ({result['device']})", "",
             f"python {env['python']}, torch {env['torch']}, CUDA {env.get('cuda_version', '-')}, "
             f"{env.get('gpu', 'no GPU')} ({env.get('gpu_memory_gb', '-')} GB)", ""]
    if "tests" in result:
        t = result["tests"]
        last = [x for x in t["tail"].splitlines() if x.strip()][-1:] or ["(no output)"]
        lines += [f"* `pytest -m gpu`: rc {t['rc']} in {t['seconds']} s: {last[0]}"]
    for color, r in result.get("model", {}).items() if "error" not in result.get("model", {}) else ():
        rows = [" ".join(x.split()) for x in r["tail"].splitlines()
                if x.strip().startswith(("training", "inference", "peak"))]
        lines += [f"* benchmarks.model, profile=paper, color={color}: rc {r['rc']}; " + "; ".join(rows)]
    run = result.get("run", {})
    if "error" in run:
        lines += [f"* runs: {run['error']}"]
    for name, r in run.items() if "error" not in run else ():
        t = r.get("timings", {})
        per_step = t.get("time/train_s", float("nan")) / max(result["steps"], 1)
        rr = {k: None if v is None else round(v, 3) for k, v in sorted(r.get("metrics", {}).items())
              if k.endswith("rr_5000")}
        lines += [f"* run {name} (paper-sized networks, tiny data, {result['steps']} steps, {result['eval_pairs']} "
                  f"+ {result['eval_pairs']} test pairs): rc {r['rc']} in {r['seconds']} s; training "
                  f"{t.get('time/train_s', float('nan')):.1f} s ({per_step:.3f} s/step), evaluation "
                  f"{t.get('time/evaluate_s', float('nan')):.1f} s; {rr}"]
    return "\n".join(lines) + "\n"


def download_wheels(folder: Path) -> None:
    """The wheels the device image lacks (:data:`WHEELS`) into ``folder``: pure Python, so a wheel made here serves
    the device's Python too (antlr4's runtime is published as source only and is built into one)."""
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(folder), *WHEELS], check=True)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m pcrcg.benchmarks.gpu_check", description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "gpu_check",
                    help="where the steps write (runs, checkpoints, logs)")
    ap.add_argument("--copy-to", type=Path, default=None, metavar="DIR",
                    help="also copy the figures and the steps' logs (at most 7 files) into DIR (the device's $OUT)")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--eval-pairs", type=int, default=20)
    ap.add_argument("--skip", default="", help=f"comma-separated steps to leave out: {','.join(STEPS)}")
    ap.add_argument("--timeout", type=float, default=200.0, help="seconds each step may take")
    ap.add_argument("--download-wheels", type=Path, default=None, metavar="DIR",
                    help="only fetch the wheels the device lacks into DIR (here, where pip reaches the registries)")
    a = ap.parse_args(argv)
    if a.download_wheels:
        download_wheels(a.download_wheels)
        return
    skip = [s for s in a.skip.split(",") if s]
    bad = [s for s in skip if s not in STEPS]
    if bad:
        raise SystemExit(f"--skip: unknown step(s) {bad}; steps: {','.join(STEPS)}")
    if a.steps < 1 or a.eval_pairs < 1:
        raise SystemExit("--steps and --eval-pairs must be at least 1")
    res = check(a.out, a.device, a.steps, a.eval_pairs, skip, timeout=a.timeout, copy_to=a.copy_to)
    print(summary(res))
    print(f"[gpu_check] figures in {a.out / 'gpu_check.json'}")


if __name__ == "__main__":
    main()
