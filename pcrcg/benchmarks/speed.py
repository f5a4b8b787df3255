"""A cpu-profile run's speed in one command: the training step with the previous and today's code, evaluation
per pair at every N before and after the exact shortcuts, and a whole run's stages against the figures of the
day the speed work began (prints figures; asserts nothing).

    python -m pcrcg.benchmarks.speed [--profile cpu] [--colors none,deep] [--checkpoint CKPT]
        [--run [--cold]] [--store URI [--code-version V]] [--pairs 4] [--eval-pairs 4] [--reps 2] [--skip train,eval] [--ransac]

1. **Training step**, old (KPConv implementation ``dense``: the previous gathers, norms, attention and losses,
   kept callable) against new (today's default), interleaved step by step, wall and process CPU, with the
   largest difference of their inferences (``python -m pcrcg.benchmarks.model compare=true``, one child
   process per color: ``none`` is geometry-only Predator, ``deep`` lifts the 2D encoder's features).
2. **Evaluation per pair at every N** (``--checkpoint``: a trained model): inference, then registration before
   (every sampled row matched, every point of every hypothesis scored) and after (the defaults) with the run's
   Open3D 0.10 budget and the profile's RANSAC distance, and whether the transforms are identical
   (``python -m pcrcg.benchmarks.evaluation``).
3. **A whole run's stages**, wall and CPU seconds (``time/<stage>_s`` and ``time/<stage>_cpu_s``,
   :class:`pcrcg.pipeline.Clock`):

   * ``--run``: runs the reference workload (:data:`REFERENCE`: 300 training steps, i.e. 2 epochs of the cpu
     profile's 150 batches, and 90 + 90 test pairs) per color with ``python -m pcrcg.run``, in a store, a
     checkpoint folder and an output folder of its own (a temporary folder, removed after): nothing of the
     repository's ``checkpoints/`` or MLflow store is read or written, but for the Pri3D weights a deep run
     loads (the default file; missing: the deep run is skipped, with the command that makes them), the
     2D match cache (``cache/matches``) and the neighbour pyramids kept between runs (the profile's
     ``train.pyramid_cache``, ``cache/pyramids`` at the cpu profile), both as the run finds them (a sweep's runs
     share them; ``--cold``: empty ones of its own);
   * ``--store``: reads the finished runs of a store instead (the newest per experiment, features and RANSAC
     ranking; ``--code-version``: only that code's) and scales their CPU per training step and per evaluated
     pair to the reference workload. A full run caches the neighbour pyramids over 12 epochs, which the
     2-epoch reference cannot, so the scaled training is a little cheaper than ``--run``'s.

4. **The summary**: the reference day's seconds, today's, the speed-up and the target (a third of the day's
   time geometry-only, half of it with deep color), met or missed. The reference day's seconds were measured on
   that day's machine; ``--reference none=S`` puts in their place the reference day's code measured on this one
   (README "Speed": 359 s on the Intel machine of 2026-12-07, where the reference day's machine took 450 s).
   CPU seconds are what a run costs on a core of its own; wall seconds on a shared machine add the time it
   waited for one.
5. **RANSAC against Open3D** (``--ransac``): both on identical correspondences at confidence 0.999, per N, with
   their recalls (``python -m pcrcg.benchmarks.registration --identical-only``: ``--ransac-pairs`` pairs x
   ``--ransac-seeds`` seeds), and whether ours is at least :data:`RANSAC_TARGET` times as fast.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Mapping, Sequence

REPO = Path(__file__).resolve().parents[2]

# The day the speed work began (2026-11, the issue "Speed: a cpu-profile run in a third of today's time"):
# a cpu-profile run of 300 training steps and ~180 test pairs with the paper's RANSAC ranking took, data
# prepared, ~270 s of training geometry-only and ~480 s with deep color (1.6 s/step), and ~180 s of evaluation
# (~1 s per pair for the five N). ``target`` is the share of that day's seconds a run may take today.
REFERENCE: dict[str, Any] = {
    "steps": 300, "pairs": 180, "epochs": 2, "max_pairs": 90,
    "none": {"train_s": 270.0, "evaluate_s": 180.0, "target": 1 / 3},
    "deep": {"train_s": 480.0, "evaluate_s": 180.0, "target": 1 / 2},
}
# the overrides that make a color's run: deep is PCR-CG as the main table runs it (conf/experiment/main_results)
COLOR_OVERRIDES = {
    "none": [],
    "deep": ["features=deep", "encoder2d=pri3d", "projection=explicit", "matcher2d=lightglue"],
}
STAGES = ("prepare", "check_inputs", "train", "evaluate", "total")
RANSAC_TARGET = 3.0  # ours at least this many times as fast as Open3D's RANSAC on identical correspondences


def _child(cmd: list[str], env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, cwd=REPO,
                          env={**os.environ, "PYTHONWARNINGS": "ignore", **(env or {})})


# --------------------------------------------------------------------------- 1. the training step


def training_step(profile: str, color: str, pairs: int, reps: int) -> dict[str, Any] | None:
    """``pcrcg.benchmarks.model``'s row for Predator at ``profile`` and ``color`` with ``compare=true`` (its
    ``old_vs_new``: median (wall, CPU) seconds per step of each implementation), None when it failed."""
    import contextlib
    import io

    from pcrcg.benchmarks.model import main as model_main

    with contextlib.redirect_stdout(io.StringIO()):  # its own printout: this benchmark prints the comparison
        rows = model_main([f"profiles=[{profile}]", "models=[predator]", f"color={color}", f"pairs={pairs}",
                           f"reps={reps}", "compare=true", "threads=1"])
    return rows[0] if rows else None


# --------------------------------------------------------------------------- 2. evaluation


def evaluation(checkpoint: str, root: str, pairs: int) -> dict[str, Any]:
    """Inference seconds per pair and :func:`pcrcg.benchmarks.evaluation.registration_speed` at the run's
    budget, with the checkpoint's own RANSAC distance (2x its voxel) and the paper's ranking (overlap)."""
    from pcrcg.benchmarks.evaluation import infer_outputs, registration_speed
    from pcrcg.device import cpu_threads
    from pcrcg.models.train import load_module

    with cpu_threads(1):  # torch's and the native pools, as a cpu-profile run (python -m pcrcg.benchmarks.evaluation)
        module = load_module(checkpoint, "cpu")
        outs, s_infer, cpu_infer = infer_outputs(module, root, pairs)
        distance = 2.0 * float(module.hparams["model"]["voxel_size"])  # the run's eval.ransac_distance
        return {"infer_s_per_pair": s_infer, "infer_cpu_s_per_pair": cpu_infer, "pairs": len(outs),
                "distance": distance, "registration": registration_speed(outs, distance)}


# --------------------------------------------------------------------------- 3. whole runs


def stage_rows(uri: str, code: str | None = None) -> list[dict[str, Any]]:
    """One row per finished run of the store that logged its stages (the newest per experiment, features and
    RANSAC ranking; only ``code``'s when given): ``{"experiment", "name", "features", "score", "code", "steps",
    "pairs", "wall": {stage: s}, "cpu": {stage: s}}`` (``cpu`` empty for runs of code before 2026-12-05,
    which logged wall seconds only; ``pairs``: the test pairs of the generated benchmarks evaluated)."""
    from pcrcg.pipeline import run_seconds
    from pcrcg.tracking.store import client, require_store
    from pcrcg.tracking.tracker import TAG_CODE

    require_store(uri)
    c = client(uri)
    names = {e.experiment_id: e.name for e in c.search_experiments()}
    newest: dict[tuple[str, str, str], dict[str, Any]] = {}
    for r in c.search_runs(list(names), filter_string="attributes.status = 'FINISHED'", max_results=50000,
                           order_by=["attributes.start_time DESC"]):
        m, p = r.data.metrics, r.data.params
        if "time/train_s" not in m or (code and r.data.tags.get(TAG_CODE) != code):
            continue
        if p.get("method", "learned") != "learned" or "train/global_step" not in m:
            continue
        exp = names[r.info.experiment_id]
        key = (exp, p.get("features.name", "none"), p.get("registration.ransac.score", "overlap"))
        if key in newest:
            continue
        newest[key] = {
            "experiment": exp, "name": r.info.run_name or "", "features": key[1], "score": key[2],
            "code": r.data.tags.get(TAG_CODE, "?"), "steps": int(m["train/global_step"]),
            "pairs": int(sum(v for k, v in m.items() if k.count("/") == 1 and k.endswith("/n_pairs"))),
            "wall": {s: run_seconds(m, s) for s in STAGES if f"time/{s}_s" in m},
            "cpu": {s: run_seconds(m, s, cpu=True) for s in STAGES if f"time/{s}_cpu_s" in m},
        }
    return list(newest.values())


def scaled(row: dict[str, Any], steps: int = REFERENCE["steps"], pairs: int = REFERENCE["pairs"]) -> dict[str, float]:
    """A run's training and evaluation seconds (CPU where logged, else wall) scaled to ``steps`` training steps
    and ``pairs`` test pairs: ``{"train_s", "evaluate_s", "per_step_s", "per_pair_s", "kind"}``."""
    src, kind = (row["cpu"], "cpu") if {"train", "evaluate"} <= row["cpu"].keys() else (row["wall"], "wall")
    per_step = src["train"] / max(row["steps"], 1)
    per_pair = src["evaluate"] / max(row["pairs"], 1)
    return {"train_s": per_step * steps, "evaluate_s": per_pair * pairs, "per_step_s": per_step,
            "per_pair_s": per_pair, "kind": kind}


def pri3d_weights(profile: str) -> Path:
    """The default Pri3D weights a deep run of ``profile`` loads (conf/encoder2d/pri3d.yaml)."""
    from pcrcg.config import load_run_config

    cfg = load_run_config([f"profile={profile}", *COLOR_OVERRIDES["deep"]], validate=False)
    path = Path(str(cfg.encoder2d.weights))
    return path if path.is_absolute() else REPO / path


def reference_run(profile: str, color: str, tmp: Path, cold: bool = False) -> tuple[dict[str, Any] | None, str]:
    """Runs the reference workload for ``color`` in ``tmp`` (its own store, checkpoints and outputs; ``cold``:
    its own empty 2D match cache and pyramid folder too, else the repository's as the run finds them) and returns its
    :func:`stage_rows` row and a one-line account (the failure's tail when it failed)."""
    over = [f"profile={profile}", f"profile.train.max_epochs={REFERENCE['epochs']}",
            f"eval.max_pairs={REFERENCE['max_pairs']}", "runtime.report_on_end=false",
            "runtime.reuse_checkpoints=false", f"paths.checkpoints={tmp / 'checkpoints'}",
            f"hydra.run.dir={tmp / 'outputs' / color}", f"experiment_name=speed_{color}", *COLOR_OVERRIDES[color]]
    if color == "deep":
        weights = pri3d_weights(profile)
        if not weights.is_file():
            return None, (f"skipped: no Pri3D weights at {weights} (make them: python -m pcrcg.pretrain2d "
                          f"profile={profile})")
        over.append(f"encoder2d.weights={weights}")
        if cold:
            over.append(f"matcher2d.cache_dir={tmp / f'matches-{color}'}")
    if cold:
        over.append(f"trainer.cache_dir={tmp / f'pyramids-{color}'}")
    uri = f"sqlite:///{tmp / 'speed.db'}"
    res = _child([sys.executable, "-m", "pcrcg.run", *over], env={"MLFLOW_TRACKING_URI": uri})
    if res.returncode != 0:
        tail = (res.stderr.strip().splitlines() or res.stdout.strip().splitlines() or ["no output"])[-1]
        return None, f"failed (exit {res.returncode}): {tail}"
    rows = [r for r in stage_rows(uri) if r["experiment"] == f"speed_{color}"]
    return (rows[0], "python -m pcrcg.run " + " ".join(over)) if rows else (None, "finished without stage metrics")


# --------------------------------------------------------------------------- printing


def _print_training(color: str, row: dict[str, Any] | None) -> None:
    if not row or not row.get("old_vs_new"):
        print(f"  color={color}: failed (python -m pcrcg.benchmarks.model color={color} says why)")
        return
    cmp = row["old_vs_new"]
    for k, label in (("train", "training step"), ("infer", "inference")):
        (ow, oc), (nw, nc) = cmp[k]["old"], cmp[k]["new"]
        print(f"  color={color:<5s} {label:<14s} wall old {ow:.3f} new {nw:.3f} s ({ow / nw:.2f}x)   "
              f"CPU old {oc:.3f} new {nc:.3f} s ({oc / nc:.2f}x)")
    print(f"  color={color:<5s} largest |old - new| of the inferences' outputs: {cmp['max_output_diff']:.1e}")


def _print_stages(row: dict[str, Any], origin: str) -> None:
    print(f"  {row['experiment']}: {row['name'] or '?'} (features={row['features']}, ranking={row['score']}, code "
          f"{row['code']}; {origin}): "
          f"{row['steps']} steps, {row['pairs']} test pairs")
    for kind in ("wall", "cpu"):
        if row[kind]:
            print(f"    {kind:<4s} " + "  ".join(f"{s} {row[kind][s]:.1f} s" for s in STAGES if s in row[kind]))


def summary(rows: dict[str, dict[str, float]], here: Mapping[str, float] | None = None) -> list[str]:
    """The summary lines: per color, the reference day's training + evaluation seconds, today's
    (``rows[color]``: :func:`scaled`), the speed-up and the target. ``here`` (color -> seconds): the reference
    day's training + evaluation measured on this machine (its code run beside today's: README "Speed") in place of
    :data:`REFERENCE`'s, which were measured on the reference day's machine; such a row says ``here``."""
    here = dict(here or {})
    lines = ["| color | reference day s | today s (train + evaluate) | speed-up | target | |",
             "|---|---:|---:|---:|---:|---|"]
    for color, now in rows.items():
        ref = REFERENCE[color]
        before, after = here.get(color, ref["train_s"] + ref["evaluate_s"]), now["train_s"] + now["evaluate_s"]
        target = before * ref["target"]
        verdict = "met" if after <= target else f"missed by {after - target:.0f} s"
        where = " (here)" if color in here else ""
        lines.append(f"| {color} | {before:.0f}{where} | {after:.0f} ({now['train_s']:.0f} + {now['evaluate_s']:.0f}, "
                     f"{now['kind']}) | {before / after:.2f}x | <= {target:.0f} s ({1 / ref['target']:.0f}x) | "
                     f"{verdict} |")
    return lines


def _reference_seconds(text: str) -> dict[str, float]:
    """``--reference`` ``"none=359,deep=700"`` -> {color: seconds}; a bad item is one line naming it."""
    from pcrcg.errors import ConfigError

    out: dict[str, float] = {}
    for item in (t.strip() for t in text.split(",") if t.strip()):
        color, _, value = item.partition("=")
        try:
            seconds = float(value)
        except ValueError:
            seconds = float("nan")
        if color not in COLOR_OVERRIDES or not seconds > 0:
            raise ConfigError("--reference", item, f"COLOR=SECONDS with COLOR one of {' | '.join(COLOR_OVERRIDES)} "
                              "and SECONDS > 0")
        out[color] = seconds
    return out


def ransac_lines(rows: Sequence[dict[str, Any]], target: float = RANSAC_TARGET) -> list[str]:
    """The RANSAC table from :func:`pcrcg.benchmarks.registration.main`'s rows: per N our and Open3D's wall and
    CPU seconds and recalls on identical correspondences, Open3D / ours by each, and the target met or missed by
    each (wall time is what a user waits; CPU time what a core spends, and what a busy machine inflates less)."""
    lines = ["| N | ours s (cpu s) | ours RR % | Open3D s (cpu s) | Open3D RR % | Open3D / ours, wall | target, wall "
             "| Open3D / ours, cpu | target, cpu |", "|---:|---:|---:|---:|---:|---:|---|---:|---|"]
    for r in rows:
        wall = r["same_open3d_s"] / r["same_ours_s"]
        cpu = r["same_open3d_cpu_s"] / r["same_ours_cpu_s"]
        lines.append(f"| {r['n_points']} | {r['same_ours_s']:.4f} ({r['same_ours_cpu_s']:.4f}) | {r['same_ours_rr']:.1f} | "
                     f"{r['same_open3d_s']:.4f} ({r['same_open3d_cpu_s']:.4f}) | {r['same_open3d_rr']:.1f} | {wall:.1f}x | "
                     f"{'met' if wall >= target else 'missed'} (>= {target:g}x) | {cpu:.1f}x | "
                     f"{'met' if cpu >= target else 'missed'} |")
    return lines


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(prog="python -m pcrcg.benchmarks.speed", description=__doc__.split("\n")[0])
    p.add_argument("--profile", default="cpu")
    p.add_argument("--colors", default="none,deep", help="none (geometry-only) and/or deep")
    p.add_argument("--checkpoint", default=None, help="a trained model for the evaluation section")
    p.add_argument("--root", default=None, help="its test data (default: data/synthmatch-<profile>)")
    p.add_argument("--run", action="store_true", help="run the reference workload per color (minutes each)")
    p.add_argument("--cold", action="store_true", help="with --run: an empty 2D match cache (LightGlue runs on "
                   "every view pair) and pyramid folder instead of cache/matches and cache/pyramids as found")
    p.add_argument("--store", default=None, help="read whole runs' stages from this tracking store instead")
    p.add_argument("--code-version", default=None, help="with --store: only this code version's runs")
    p.add_argument("--pairs", type=int, default=4, help="training pairs timed per step")
    p.add_argument("--eval-pairs", type=int, default=4, help="test pairs per benchmark timed in evaluation")
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--skip", default="", help="train and/or eval")
    p.add_argument("--reference", default="", metavar="COLOR=SECONDS[,...]",
                   help="the reference day's training + evaluation seconds measured on this machine (its code run "
                        "beside today's, README 'Speed'), e.g. none=359, in place of the figures of the reference "
                        "day's machine")
    p.add_argument("--ransac", action="store_true", help="also RANSAC against Open3D on identical correspondences")
    p.add_argument("--ransac-pairs", type=int, default=32)
    p.add_argument("--ransac-seeds", type=int, default=3)
    args = p.parse_args(argv)

    from pcrcg.errors import ConfigError

    colors = [c for c in args.colors.split(",") if c]
    for c in colors:
        if c not in COLOR_OVERRIDES:
            raise ConfigError("--colors", c, " | ".join(COLOR_OVERRIDES))
    for name in ("pairs", "eval_pairs", "reps", "ransac_pairs", "ransac_seeds"):
        if getattr(args, name) < 1:
            raise ConfigError("--" + name.replace("_", "-"), getattr(args, name), "an integer >= 1")
    here = _reference_seconds(args.reference)
    bad = [k for k in args.skip.split(",") if k and k not in ("train", "eval")]
    if bad:
        raise ConfigError("--skip", args.skip, "train and/or eval, comma-separated")
    if args.checkpoint and not Path(args.checkpoint).is_file():
        raise ConfigError("--checkpoint", args.checkpoint, "an existing model.ckpt")
    if args.store:
        from pcrcg.tracking.store import require_store

        require_store(args.store, "--store")
    skip = set(args.skip.split(","))
    out: dict[str, Any] = {"training": {}, "evaluation": None, "runs": {}, "summary": {}}

    if "train" not in skip:
        print(f"1. Training step, {args.profile} profile, Predator, {args.pairs} pairs x {args.reps} rounds, 1 thread, "
              "median s per step (old: the previous code, KPConv implementation dense; new: today's)")
        for c in colors:
            out["training"][c] = row = training_step(args.profile, c, args.pairs, args.reps)
            _print_training(c, row)

    if "eval" not in skip:
        if args.checkpoint:
            root = args.root or str(REPO / "data" / f"synthmatch-{args.profile}")
            out["evaluation"] = ev = evaluation(args.checkpoint, root, args.eval_pairs)
            print(f"\n2. Evaluation, {ev['pairs']} test pairs of {root}: inference {ev['infer_s_per_pair']:.3f} s/pair "
                  f"(CPU {ev['infer_cpu_s_per_pair']:.3f}); "
                  f"registration at the run's budget, RANSAC distance {ev['distance']:.3f} m, the paper's ranking")
            from pcrcg.benchmarks.evaluation import BUDGETS, print_registration

            print_registration(BUDGETS[0][0], ev["registration"])
        else:
            print("\n2. Evaluation: skipped (--checkpoint a trained model.ckpt)")

    print(f"\n3. Whole runs (reference workload: {REFERENCE['steps']} training steps, {REFERENCE['pairs']} test pairs)")
    if args.run:
        with tempfile.TemporaryDirectory(prefix="pcrcg-speed-") as tmp:
            for c in colors:
                row, how = reference_run(args.profile, c, Path(tmp), args.cold)
                print(f"  color={c}: {how}")
                if row:
                    _print_stages(row, "run here")
                    out["runs"][c] = row
                    out["summary"][c] = scaled(row, row["steps"], row["pairs"])
    elif args.store:
        for row in stage_rows(args.store, args.code_version):
            _print_stages(row, f"from {args.store}")
            s = scaled(row)
            print(f"    per step {s['per_step_s']:.3f} s, per test pair {s['per_pair_s']:.3f} s ({s['kind']}); scaled to "
                  f"the reference workload: train {s['train_s']:.0f} s + evaluate {s['evaluate_s']:.0f} s")
            if row["features"] in colors and row["features"] not in out["summary"] and row["score"] == "overlap":
                out["runs"][row["features"]], out["summary"][row["features"]] = row, s
        if not out["summary"]:
            print("  no run of the store ranks RANSAC's hypotheses by overlap (the paper's protocol, which the reference "
                  "day's evaluation used): no summary")
    else:
        print("  skipped (--run: run the reference workload here; --store URI: read a store's finished runs)")

    if out["summary"]:
        print("\n4. Summary (the reference day's figures: pcrcg.benchmarks.speed.REFERENCE; the paper's ranking)")
        print("\n".join(summary(out["summary"], here)))
    if args.ransac:
        from pcrcg.benchmarks.registration import main as registration_main

        print(f"\n5. RANSAC against Open3D on identical correspondences ({args.ransac_pairs} pairs x {args.ransac_seeds} "
              "seeds, confidence 0.999)")
        got = registration_main(["--identical-only", "--pairs", str(args.ransac_pairs), "--seeds", str(args.ransac_seeds)])
        out["ransac"] = got["rows"]
        print("\n".join(ransac_lines(got["rows"])))
    print("\n@@" + json.dumps(out, default=str))
    return out


if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.benchmarks.speed"):  # a bad file or setting: one line, exit 2
        main()
