"""Speed and memory of the 3D network stage (prints figures; asserts nothing).

``python -m pcrcg.benchmarks.model [profiles=[tiny,cpu]] [models=[predator,geotransformer]] [pairs=4]
[reps=3] [device=cpu] [threads=1] [root=null] [color=none|rgb|deep] [breakdown=false] [matchability=false]``

Per profile and model (sizes from ``conf/profile/<p>.yaml`` + ``conf/model/<model>.yaml``), on the
generated data set ``data/synthmatch-<p>`` when it exists (else a synthetic box-room pair sized for
the profile's voxel, said so in the output):

* data pipeline, seconds per pair: the collate step (grid subsampling, radius neighbours of every
  level, correspondences, augmentation) with an empty neighbour cache (``cold``) and with the
  fragments' pyramids cached (``warm``, what training sees from the second epoch on);
* training, seconds per pair: forward + losses + backward + optimiser step (the profile's);
* inference, seconds per pair: forward without gradients and the per-fragment outputs;
* peak memory: the process's peak RSS (CPU) or ``torch.cuda.max_memory_allocated`` (GPU);
* ``breakdown=true``: the training step by stage (torch.profiler over the model's labelled scopes);
* ``matchability=true``: the training step with Predator's matchability loss on (its gate open, as once
  the validation recall passes ``loss.matchability_after_recall``: the later part of a run, and every
  validation step), which adds the matchability labels (arg-maxes of an overlap x overlap score matrix).

``compare=true`` (the default) times the training step and inference twice, interleaved step by
step in one process: ``old`` with the previous code (``pcrcg.models.kpconv`` implementation
``dense``: padded neighbour gathers, the reference max-pool backward, ``torch.var_mean`` norms, the
attention's (N, k, 2C) edge features and a k-NN graph per layer, the circle loss in plain autograd
operations, the matchability labels' full score matrix) and ``new`` with the default (``auto``: the
sparse aggregation on the CPU, two-pass norms with a closed-form backward, per-point edge products and
shared k-NN graphs, the fused circle-loss log-sum-exps, the labels' arg-maxes by blocks), and prints
both side by side with the speed-up and
the largest difference of the two inferences' descriptors (float rounding only). Every step starts
from an empty per-batch KPConv cache, as in a run, where every batch is a new pair, and every inference
without GeoTransformer's kept embeddings (a run's evaluation reuses a fragment's in its other pairs: the
benchmark's rounds over the same pairs would all hit). For GeoTransformer ``old`` also runs the relative-position
scores as the einsum they were (:class:`pcrcg.models.geotransformer.transformer._RelativeScores`). Wall time
(median) and the process's CPU time (median, steadier on a shared machine) are both given.

Each profile runs in its own process so that the peak memory is its own.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

CONF = Path(__file__).resolve().parents[2] / "conf"
REPO = CONF.parent


def _interleaved(step: Callable[[Any], Any], batches: list, reps: int) -> dict[str, tuple[float, float]]:
    """Median (wall, process CPU) seconds of ``step(batch)`` under each of :data:`IMPLS`, the
    implementations taking turns on every batch (``reps`` rounds over the batches, after a warm-up)."""
    from pcrcg.models.kpconv import implementation

    wall: dict[str, list[float]] = {k: [] for k in IMPLS}
    cpu: dict[str, list[float]] = {k: [] for k in IMPLS}
    for r in range(reps + 1):
        for b in batches:
            for name, impl in IMPLS.items():
                with implementation(impl):
                    t0, c0 = time.perf_counter(), time.process_time()
                    step(b)
                    if r:  # round 0 warms up
                        wall[name].append(time.perf_counter() - t0)
                        cpu[name].append(time.process_time() - c0)
    return {k: (float(np.median(wall[k])), float(np.median(cpu[k]))) for k in IMPLS}


# the two implementations compare=true times: the previous gathers and today's default
IMPLS = {"old": "dense", "new": "auto"}


def _time(fn: Callable[[], Any], reps: int) -> float:
    fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def model_node(model: str):
    """``conf/model/<model>.yaml`` with its ``common/<name>@_here_`` defaults merged under it (no Hydra)."""
    from omegaconf import OmegaConf

    node = OmegaConf.load(CONF / "model" / f"{model}.yaml")
    parts = []
    for d in node.pop("defaults", None) or []:
        name = str(d)
        if name != "_self_":
            parts.append(OmegaConf.load(CONF / "model" / f"{name.split('@')[0]}.yaml"))
    return OmegaConf.merge(*parts, node)


def profile_config(profile: str, model: str = "predator") -> dict[str, Any]:
    """The resolved ``model`` and ``trainer`` nodes of a profile (no Hydra needed)."""
    from omegaconf import OmegaConf

    from pcrcg.config import profile_node

    root = OmegaConf.create({
        "profile": profile_node(profile, CONF),
        "model": model_node(model),
        "trainer": OmegaConf.load(CONF / "trainer" / "default.yaml"),
    })
    return OmegaConf.to_container(root, resolve=True)  # type: ignore[return-value]


def _samples(root: Path | None, voxel: float, n: int, n_views: int) -> tuple[list, str]:
    if root is not None and (root / "pairs" / "train.txt").is_file():
        from pcrcg.data.dataset import PairDataset

        ds = PairDataset(root, "train", n_views)
        step = max(1, len(ds) // n)
        return [ds[k] for k in range(0, min(len(ds), step * n), step)][:n], f"{root} (train pairs)"
    from pcrcg.testing.pairs import toy_pair

    density = 2.0 / voxel**2
    return ([toy_pair(k, size=(4.0, 3.5, 2.6), density=density) for k in range(n)],
            f"synthetic box-room pairs ({root} not found)")


def _lifting(color: str, profile: str, model: str = "predator") -> dict | None:
    """The projection module's nodes (:func:`pcrcg.models.train.lifting_section`) as ``python -m pcrcg.run
    features=<color> projection=implicit profile=<profile> model=<model>`` composes them: the run's views and
    the profile's 2D network and image sizes (explicit adds the 2D matcher, timed by ``benchmarks.vision``)."""
    if color == "none":
        return None
    from pcrcg.config import load_run_config
    from pcrcg.models.train import lifting_section
    from pcrcg.tracking.hashing import to_plain

    cfg = load_run_config([f"profile={profile}", f"model={model}", f"features={color}", "projection=implicit"],
                          validate=False)
    return lifting_section(to_plain(cfg))


def _collate(samples: list, m: dict[str, Any], t: dict[str, Any]):
    """The training collate of the samples' pyramids (neighbour limits calibrated on them, as the data
    module does) and its time per pair without and with the pyramid cache: (collate, limits, cold, warm)."""
    from pcrcg.models.datamodule import AugmentConfig, PairCollate
    from pcrcg.models.kpconv import PyramidCache, PyramidSpec, calibrate_limits

    spec0 = PyramidSpec(m["voxel_size"], m["num_layers"], m["conv_radius"], (), m["max_points"])
    clouds = [c for s in samples for c in (s.src_points, s.tgt_points)]
    limits = calibrate_limits(clouds, spec0, m["neighbor_keep_ratio"])
    spec = PyramidSpec(m["voxel_size"], m["num_layers"], m["conv_radius"], limits, m["max_points"])
    r_ov = m["loss"].get("overlap_radius", 1.5) * m["voxel_size"]
    aug = AugmentConfig.from_mapping(t.get("augment"))

    cold = []
    for s in samples:
        col = PairCollate(spec, r_ov, aug, PyramidCache(0))
        t0 = time.perf_counter()
        col([s])
        cold.append(time.perf_counter() - t0)
    warm_col = PairCollate(spec, r_ov, aug, PyramidCache(64))
    for s in samples:
        warm_col([s])
    warm = []
    for s in samples:
        t0 = time.perf_counter()
        warm_col([s])
        warm.append(time.perf_counter() - t0)
    return warm_col, limits, cold, warm


def _step_functions(module, opt, sync):
    """One training step (forward, loss, backward, optimiser) and one inference of a batch."""

    def train_on(b):
        b.pyramid.cache.clear()  # a run's every batch is a new pair: nothing of the last step is reused
        loss = module.training_step(b, 0)
        if loss is not None:
            opt.zero_grad()
            loss.backward()
            opt.step()
        sync()

    def infer_on(b):
        b.pyramid.cache.clear()
        for m in module.modules():  # nor GeoTransformer's embeddings of the fragments seen in earlier rounds
            if hasattr(m, "clear_memo"):
                m.clear_memo()
        module.predict_pair(b)
        sync()

    return train_on, infer_on


def _time_steps(module, opt, batches, sync, reps: int, compare: bool, breakdown: bool):
    """Seconds per training step and per inference (old and new side by side when ``compare``), the
    stage breakdown when asked: (s_train, s_infer, stages, compared)."""
    train_on, infer_on = _step_functions(module, opt, sync)
    it = iter(range(10**9))
    compared: dict[str, Any] = {}
    module.train()
    if compare:
        compared["train"] = _interleaved(train_on, batches, reps)
        s_train = compared["train"]["new"][0]
    else:
        s_train = _time(lambda: train_on(batches[next(it) % len(batches)]), reps * len(batches))
    stages = _breakdown(module, opt, batches, sync, reps) if breakdown else None
    module.eval()
    if compare:
        compared["infer"] = _interleaved(infer_on, batches, reps)
        s_infer = compared["infer"]["new"][0]
        compared["max_output_diff"] = _max_output_diff(module, batches)
    else:
        s_infer = _time(lambda: infer_on(batches[next(it) % len(batches)]), reps * len(batches))
    return s_train, s_infer, stages, compared


def bench_profile(profile: str, pairs: int = 4, reps: int = 3, device: str = "cpu", root: str | None = None,
                  color: str = "none", breakdown: bool = False, model: str = "predator",
                  compare: bool = True, matchability: bool = False) -> dict[str, Any]:
    """One profile's figures: the data pipeline, the training step and inference on ``pairs`` training
    pairs of its data set (``root``; else generated box rooms), memory, and the optional breakdown."""
    import torch

    from pcrcg.models.module import PCRCGModule

    cfg = profile_config(profile, model)
    m, t = cfg["model"], cfg["trainer"]
    data_root = Path(root) if root else REPO / "data" / f"synthmatch-{profile}"
    lifting = _lifting(color, profile, model)
    samples, source = _samples(data_root, m["voxel_size"], pairs, int(lifting["projection"]["views"]) if lifting else 0)
    collate, limits, cold, warm = _collate(samples, m, t)

    torch.manual_seed(0)
    module = PCRCGModule({**m, "neighbor_limits": list(limits)}, optim=t.get("optim"), lifting=lifting).to(device)
    if matchability and hasattr(module, "matchability_gate"):
        module.matchability_gate.fill_(1.0)
    opt = module.configure_optimizers()["optimizer"]
    batches = [collate([s]).to(device) for s in samples]
    sync = (lambda: torch.cuda.synchronize()) if device.startswith("cuda") else (lambda: None)
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    s_train, s_infer, stages, compared = _time_steps(module, opt, batches, sync, reps, compare, breakdown)

    n0 = [int(b.pyramid.lengths[0].sum()) for b in batches]
    peak = (torch.cuda.max_memory_allocated() / 2**20 if device.startswith("cuda")
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return {
        "profile": profile, "model": model, "device": device, "data": source, "color": color, "pairs": len(samples),
        "voxel": m["voxel_size"], "levels": m["num_layers"], "first_dim": m["first_dim"],
        "params": sum(p.numel() for p in module.net.parameters()),
        "in_dim": module.in_dim, "level0_points_per_pair": float(np.mean(n0)), "neighbor_limits": list(limits),
        "data_s_per_pair_cold": float(np.mean(cold)), "data_s_per_pair_warm": float(np.mean(warm)),
        "train_s_per_pair": s_train, "infer_s_per_pair": s_infer, "optimizer": type(opt).__name__,
        "peak_mem_mb": peak, "peak_mem_kind": "cuda allocated" if device.startswith("cuda") else "process RSS",
        "torch_threads": torch.get_num_threads(), "stages_ms_per_step": stages, "old_vs_new": compared or None,
        "matchability": bool(matchability),
    }


def _max_output_diff(module, batches) -> float:
    """Largest |old - new| over the descriptors, overlap and matchability of the batches' inference."""
    import torch

    from pcrcg.models.kpconv import implementation

    worst = 0.0
    for b in batches:
        outs = []
        for impl in IMPLS.values():
            b.pyramid.cache.clear()
            with implementation(impl), torch.no_grad():
                o = module.predict_pair(b)
            outs.append(np.concatenate([np.concatenate([f.descriptors, f.overlap[:, None], f.matchability[:, None]], 1)
                                        for f in (o.src, o.tgt)]))
        worst = max(worst, float(np.abs(outs[0] - outs[1]).max()))
    b.pyramid.cache.clear()
    return worst


def _breakdown(module, opt, batches, sync, reps: int) -> dict[str, float]:
    """Milliseconds per training step in each labelled stage (``torch.profiler.record_function``
    scopes in the model code: 2D encoder + lifting, KPConv kernel weights, neighbour gathers and
    aggregation, attention, decoder, losses) and in the step's forward, backward and optimiser.
    Stage times include their children; the KPConv rows are parts of the encoder and decoder rows."""
    from torch.profiler import ProfilerActivity, profile, record_function

    n = reps * len(batches)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for k in range(n):
            b = batches[k % len(batches)]
            b.pyramid.cache.clear()
            with record_function("step.forward + losses"):
                loss = module.training_step(b, 0)
            if loss is None:
                continue
            with record_function("step.backward"):
                opt.zero_grad()
                loss.backward()
            with record_function("step.optimizer"):
                opt.step()
            sync()
    out = {}
    for ev in prof.key_averages():
        if ev.key.startswith(("pcrcg.", "step.")):
            out[ev.key] = ev.cpu_time_total / 1e3 / n
    return dict(sorted(out.items(), key=lambda kv: (not kv[0].startswith("step."), -kv[1])))


def _parse(argv: list[str]) -> dict[str, Any]:
    from omegaconf import OmegaConf

    args = {"profiles": ["tiny", "cpu"], "models": ["predator", "geotransformer"], "pairs": 4, "reps": 3,
            "device": "cpu", "threads": 1, "root": None, "color": "none", "child": False, "breakdown": False,
            "compare": True, "matchability": False}
    for a in argv:
        k, _, v = a.partition("=")
        if k not in args:
            raise SystemExit(f"unknown argument {k!r}; known: {sorted(args)}")
        val = OmegaConf.to_container(OmegaConf.create(f"v: {v}"))["v"] if v else v  # type: ignore[index]
        args[k] = val
    for k in ("profiles", "models"):
        if isinstance(args[k], str):
            args[k] = [args[k]]
    for m in args["models"]:
        if not (CONF / "model" / f"{m}.yaml").is_file():
            raise SystemExit(f"models: unknown model {m!r} (conf/model/<name>.yaml)")
    return args


def _print(row: dict[str, Any]) -> None:
    print(f"\n[{row['profile']}] model={row.get('model', 'predator')}, {row['device']}, {row['data']}, color={row['color']}")
    print(f"  model: voxel {row['voxel']} m, {row['levels']} levels, first_dim {row['first_dim']}, "
          f"{row['params'] / 1e6:.2f} M params, in_dim {row['in_dim']}; "
          f"{row['level0_points_per_pair']:.0f} level-0 points per pair; limits {row['neighbor_limits']}")
    print(f"  data pipeline  {row['data_s_per_pair_cold']:.3f} s/pair cold, {row['data_s_per_pair_warm']:.3f} s/pair warm")
    ml = ", matchability loss on" if row.get("matchability") else ""
    print(f"  training       {row['train_s_per_pair']:.3f} s/pair (forward + loss + backward + {row['optimizer']}{ml})")
    print(f"  inference      {row['infer_s_per_pair']:.3f} s/pair")
    print(f"  peak memory    {row['peak_mem_mb']:.0f} MB ({row['peak_mem_kind']}), {row['torch_threads']} torch threads")
    cmp = row.get("old_vs_new")
    if cmp:
        print("  old vs new (KPConv implementation dense = previous code | auto), interleaved, median s/pair:")
        for k, label in (("train", "training step"), ("infer", "inference")):
            (ow, oc), (nw, nc) = cmp[k]["old"], cmp[k]["new"]
            print(f"    {label:<14s} wall  old {ow:.3f}  new {nw:.3f}  ({ow / nw:.2f}x)   "
                  f"cpu  old {oc:.3f}  new {nc:.3f}  ({oc / nc:.2f}x)")
        print(f"    outputs: largest |old - new| over descriptors, overlap, matchability = {cmp['max_output_diff']:.1e}")
    if row.get("stages_ms_per_step"):
        print("  training step by stage (torch.profiler, ms per step; stages include their children):")
        for k, v in row["stages_ms_per_step"].items():
            print(f"    {k:<48s} {v:9.1f}")


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    args = _parse(list(sys.argv[1:] if argv is None else argv))
    import torch

    torch.set_num_threads(int(args["threads"]))
    from pcrcg.device import keep_freed_memory

    keep_freed_memory()  # the heap as a run keeps it (PCRCG_MALLOC=default: glibc's own settings)
    if args["child"]:
        row = bench_profile(args["profiles"][0], int(args["pairs"]), int(args["reps"]), str(args["device"]),
                            args["root"], str(args["color"]), bool(args["breakdown"]), str(args["models"][0]),
                            bool(args["compare"]), bool(args["matchability"]))
        print("@@" + json.dumps(row))
        return [row]
    rows = []
    for p in args["profiles"]:
        for model in args["models"]:  # each in its own process: its own peak memory
            cmd = [sys.executable, "-m", "pcrcg.benchmarks.model", f"profiles={p}", f"models=[{model}]", "child=true"]
            cmd += [f"{k}={args[k]}" for k in ("pairs", "reps", "device", "threads", "color", "breakdown", "compare",
                                                   "matchability")]
            if args["root"]:
                cmd.append(f"root={args['root']}")
            res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"})
            line = next((x for x in res.stdout.splitlines() if x.startswith("@@")), None)
            if line is None:
                print(f"[{p}] model={model} failed:\n{res.stderr[-3000:]}")
                continue
            row = json.loads(line[2:])
            _print(row)
            rows.append(row)
    if len(args["models"]) > 1 and rows:
        print("\nseconds per pair, side by side (training step | inference):")
        for p in args["profiles"]:
            cells = [f"{r['model']} {r['train_s_per_pair']:.3f} | {r['infer_s_per_pair']:.3f}"
                     for r in rows if r["profile"] == p]
            print(f"  [{p}] " + "    ".join(cells))
    return rows


if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.benchmarks.model"):  # a bad file or setting: one line, exit 2
        main()
