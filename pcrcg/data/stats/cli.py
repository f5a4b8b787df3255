"""``python -m pcrcg.data.stats ROOT [ROOT ...] [--out reports/data/stats] [--pairs N] [--fragments N] ...``

Prints one column per data set and writes ``<out>.md``, ``<out>.json`` and ``<out>.png``.

Columns
    Each ROOT is a data set in the 3DMatch layout (``data/synthmatch-tiny``, ``data/synthmatch-cpu``,
    ``data/redkitchen``, a real scene root made by ``python -m pcrcg.prepare data=threedmatch``).
    ``--fragments-dir DIR`` adds a column for a bare folder of ``cloud_bin_<i>.ply`` (e.g. the
    3DMatch release's), optionally with ``--frames-dir`` (its RGB-D frames, ``.color.png`` or
    ``.color.jpg``), ``--benchmarks-dir`` (``{3DMatch,3DLoMatch}/<scene>/gt.log|gt.info|gt_overlap.log``,
    scene = the folder's name) and ``--frames-per-fragment N`` (frame ranges where a fragment has no
    ``.info.txt``: fragment i = frames N*i ... N*i+N-1, 3DMatch used 50).

Rows (see :mod:`pcrcg.data.stats.measures` for the definitions)
    * fragments; points per fragment at 2.5 cm voxels (mean, p10, p90);
    * extent: sides of the PCA-aligned bounding box (sorted) and of the axis-aligned box in the
      fragment frame, each side between the 2nd and 98th percentile of the coordinates, median over
      fragments, metres (both at 2.5 cm);
    * planarity: share of the 5 cm-voxel points within 2 cm of the 4 largest planes found one after
      the other by Open3D's seeded RANSAC ``segment_plane``; median and min–max;
    * normal-orientation entropy: normals at 5 cm voxels (radius 10 cm, 30 neighbours), axial
      orientations (n = -n) binned into 200 nearly equal-area Fibonacci cells (at most 7.64 bits);
    * overlap histograms of the benchmark pairs (``gt.log`` pairs, ``gt_overlap.log`` overlaps) and of
      the training pairs (``pairs/train.txt``);
    * FPFH + RANSAC registration recall per benchmark, by the project's own
      :func:`pcrcg.evaluation.stage.run_benchmark_mode` with the settings of ``python -m pcrcg.evaluate
      mode=benchmark method=fpfh profile=<--profile>`` (the 3DMatch protocol: counted pairs are
      those with j - i > 1; recall per scene, then averaged); ``--pairs N`` pairs per benchmark,
      spread evenly over the pairs whose two fragments exist;
    * SIFT keypoints per image and verified 2D matches per view pair by
      :func:`pcrcg.vision.matching.match_images` with ``conf/matcher2d/sift.yaml``, at the
      projection's grid (``profile.lifting.image_size``, 160x120) and at the images' native size,
      for the paper's view pairs (first-first and last-last frames of the two fragments of each pair
      run; frame ids from ``cloud_bin_<i>.info.txt``), and the grid's matches per bin of the view
      pair's co-visibility (:func:`pcrcg.data.stats.measures.covisibility`: the share of the first
      frame's depth pixels that the second frame sees at a consistent depth), so that data sets whose
      pairs see each other more or less compare at equal co-visibility, and per benchmark (the view
      pairs of 3DMatch pairs and of 3DLoMatch pairs apart: a sample that mixes the two in other
      proportions than another compares like with like);
    * depth holes: share of zero-depth pixels per frame, and the frames' median depth, over at most
      ``--frames`` frames of the measured fragments.
    Image rows print "–" for a data set without RGB-D frames.

A bad ROOT or folder is a one-line error naming it (exit status 2). Measures run on one core:
``--threads`` (default 1) sets torch's threads and, unless already set, ``OMP_NUM_THREADS``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Sequence


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m pcrcg.data.stats", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Statistics of data sets side by side: one column per data set, printed as Markdown and "
                    "written to <out>.md, <out>.json and <out>.png.",
        epilog=__doc__.split("\n\n", 2)[2])
    p.add_argument("roots", nargs="*", metavar="ROOT", help="data sets in the 3DMatch layout")
    p.add_argument("--out", default="reports/data/stats", help="output prefix: <out>.md, .json, .png")
    p.add_argument("--pairs", type=int, default=30,
                   help="benchmark pairs per benchmark for the FPFH and SIFT rows (0: all; default 30)")
    p.add_argument("--fragments", type=int, default=100,
                   help="fragments measured per data set, spread evenly (0: all; default 100)")
    p.add_argument("--frames", type=int, default=200, help="depth frames for the hole rate (0: all; default 200)")
    p.add_argument("--profile", default="cpu",
                   help="conf/profile for RANSAC iterations and the projection grid (default cpu, as pcrcg.evaluate)")
    p.add_argument("--seed", type=int, default=0, help="RANSAC seeds (planes, FPFH)")
    p.add_argument("--fragments-dir", help="a bare folder of cloud_bin_<i>.ply as one more column")
    p.add_argument("--frames-dir", help="with --fragments-dir: its RGB-D frames (frame-XXXXXX.*)")
    p.add_argument("--benchmarks-dir", help="with --fragments-dir: {3DMatch,3DLoMatch}/<scene>/gt.log ...")
    p.add_argument("--frames-per-fragment", type=int, help="with --fragments-dir: frame ranges without .info.txt")
    p.add_argument("--name", help="with --fragments-dir: the column's name")
    p.add_argument("--no-fpfh", action="store_true", help="skip the FPFH + RANSAC rows")
    p.add_argument("--no-sift", action="store_true", help="skip the SIFT rows")
    p.add_argument("--no-picture", action="store_true", help="do not write <out>.png")
    p.add_argument("--threads", type=int, default=1, help="CPU threads (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def _unique_names(sources) -> None:
    seen: dict[str, int] = {}
    for s in sources:
        n = seen.get(s.name, 0)
        seen[s.name] = n + 1
        if n:
            s.name = f"{s.name} ({n + 1})"


def run(args: argparse.Namespace) -> dict:
    """Open every column (checked before work starts), measure, write; returns the JSON object."""
    from pcrcg.data.stats.collect import StatsConfig, evaluate_config, measure, preview_fragments
    from pcrcg.data.stats.report import markdown_table, picture, write_outputs
    from pcrcg.data.stats.sources import open_folder, open_root
    from pcrcg.errors import ConfigError

    if not args.roots and not args.fragments_dir:
        raise ConfigError("ROOT", None, "at least one data set root or --fragments-dir DIR")
    for flag in ("frames_dir", "benchmarks_dir", "frames_per_fragment", "name"):
        if getattr(args, flag) is not None and not args.fragments_dir:
            raise ConfigError(f"--{flag.replace('_', '-')}", getattr(args, flag), "only together with --fragments-dir")
    for flag in ("pairs", "fragments", "frames"):
        if getattr(args, flag) < 0:
            raise ConfigError(f"--{flag}", getattr(args, flag), "an integer >= 0 (0: all)")
    sources = [open_root(r) for r in args.roots]
    if args.fragments_dir:
        sources.append(open_folder(args.fragments_dir, args.frames_dir, args.benchmarks_dir,
                                   args.frames_per_fragment, args.name))
    _unique_names(sources)
    import torch  # after the inputs are checked: a bad ROOT fails fast

    torch.set_num_threads(max(args.threads, 1))
    cfg = StatsConfig(fragments=args.fragments or None, pairs=args.pairs or None, frames=args.frames or None,
                      profile=args.profile, seed=args.seed, fpfh=not args.no_fpfh, sift=not args.no_sift)
    eval_cfg = evaluate_config(cfg.profile) if cfg.fpfh else None
    progress = not args.quiet
    t0 = time.perf_counter()
    columns, previews = [], []
    from tqdm import tqdm

    for src in tqdm(sources, desc="data sets", unit="set", disable=not progress or len(sources) < 2):
        columns.append(measure(src, cfg, eval_cfg, progress))
        if not args.no_picture:
            previews.append((src.name, preview_fragments(src, cfg.preview)))
    from dataclasses import asdict

    from pcrcg.data.materialise import GENERATOR_VERSION
    from pcrcg.tracking.git import git_info

    sha, dirty = git_info()
    settings = {**asdict(cfg), "command": " ".join(["python -m pcrcg.data.stats", *sys.argv[1:]]),
                "seconds": round(time.perf_counter() - t0, 1), "code_commit": sha, "code_dirty": dirty,
                "data_code_version": GENERATOR_VERSION}
    notes = _notes(cfg) + (f"Made by commit {sha}{' with uncommitted changes' if dirty else ''} "
                           f"(data code version {GENERATOR_VERSION}).\n")
    md, js = write_outputs(columns, settings, args.out, notes)
    png = None
    if previews:
        png = picture(previews, Path(str(args.out) + ".png"))
    print(markdown_table(columns))
    print(f"wrote {md}, {js}" + (f", {png}" if png else "") + f" in {settings['seconds']} s")
    return {"settings": settings, "columns": columns}


def _notes(cfg) -> str:
    return (
        "How it was measured (see `pcrcg/data/stats/cli.py`): points at 2.5 cm voxels (Open3D); extent at 2.5 cm between the 2nd and 98th percentiles; "
        f"planarity: {cfg.n_planes} sequential Open3D `segment_plane` fits ({cfg.plane_distance * 100:.0f} cm, "
        f"{cfg.plane_iterations} iterations, seed {cfg.seed}) on 5 cm voxels; normal entropy: axial orientations of "
        f"normals at 5 cm voxels in {cfg.n_cells} axial Fibonacci cells (max "
        f"{__import__('math').log2(cfg.n_cells):.2f} bits); FPFH + RANSAC through "
        f"`pcrcg.evaluation.stage.run_benchmark_mode` (profile {cfg.profile}), at most {cfg.pairs or 'all'} pairs "
        "per benchmark, spread evenly; SIFT by `pcrcg.vision.matching` (`conf/matcher2d/sift.yaml`) on the "
        "first-first and last-last view pairs of those pairs; co-visibility: share of the first frame's depth "
        "pixels (every 2nd row and column) seen by the second within 10% of their depth; overlap counts in bins 0–10/10–30/30–50/50–70/70–100%.\n"
    )


def main(argv: Sequence[str] | None = None) -> None:
    args = parser().parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", str(max(args.threads, 1)))
    from pcrcg.errors import PcrcgError

    try:
        run(args)
    except PcrcgError as exc:  # bad input: one line naming the file or setting, no traceback
        print(f"pcrcg.data.stats: error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
