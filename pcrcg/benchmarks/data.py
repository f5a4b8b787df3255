"""Generation figures per profile: ``python -m pcrcg.benchmarks.data [--profiles tiny cpu] [--workers 2]``.

For each profile, generates the synthmatch data set into a temporary folder and prints frames/s,
fragments/s, points per fragment, pairs per split and benchmark, wall time and peak memory
(resident set of this process and its workers). Also times one frame's rendering and one
fragment's fusion in isolation. Nothing is asserted: these are figures to read.
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import numpy as np


def _peak_rss_mib() -> float:
    me = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(me, kids) / 1024.0


def _data_cfg(profile: str, root: Path, workers: int) -> dict:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("prepare", [f"profile={profile}", f"data.root={root}", f"data.workers={workers}"])
    return OmegaConf.to_container(cfg.data, resolve=True)


def micro(profile: str) -> dict:
    """Seconds to render one frame and to fuse one fragment at the profile's size."""
    from pcrcg.data.fusion import FusionConfig, fuse_frames
    from pcrcg.data.synth.camera import camera_path
    from pcrcg.data.synth.render import RoomRenderer
    from pcrcg.data.synth.scene import make_room
    from pcrcg.data.synthmatch import intrinsics_for

    with tempfile.TemporaryDirectory() as tmp:
        cfg = _data_cfg(profile, Path(tmp) / "x", 1)
    s, f = cfg["synth"], cfg["fusion"]
    rng = np.random.default_rng(0)
    room = make_room(rng)
    n = s["frames_per_fragment"]
    poses = camera_path(room, n, s["fragment_seconds"] / n, rng)
    K = intrinsics_for(s["width"], s["height"])
    r = RoomRenderer(room)
    t0 = time.perf_counter()
    frames = [r.render(P, K, s["width"], s["height"], rng) for P in poses]
    t_render = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    pts, _ = fuse_frames([c for c, _, _ in frames], [d for _, d, _ in frames], list(poses), K, FusionConfig(**f))
    t_fuse = time.perf_counter() - t0
    return {"render_s_per_frame": round(t_render, 4), "fuse_s_per_fragment": round(t_fuse, 3),
            "fused_points": int(len(pts))}


def run_profile(profile: str, workers: int) -> dict:
    from pcrcg.data.materialise import prepare_dataset, read_manifest

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / f"synthmatch-{profile}"
        cfg = _data_cfg(profile, root, workers)
        t0 = time.perf_counter()
        prepare_dataset(cfg, seed=0, log=lambda m: None)
        wall = time.perf_counter() - t0
        stats = read_manifest(root)["stats"]
    return {
        "profile": profile,
        "workers": workers,
        "wall_s": round(wall, 1),
        "frames": stats["frames"],
        "frames_per_s": round(stats["frames"] / wall, 1),
        "fragments": stats["fragments"],
        "fragments_per_s": round(stats["fragments"] / wall, 2),
        "points_per_fragment_mean": round(stats["points_per_fragment"]["mean"]),
        "pairs": stats["pairs"],
        "scenes": stats["scenes"],
        "peak_rss_mib": round(_peak_rss_mib()),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--profiles", nargs="+", default=["tiny", "cpu"])
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args(argv)
    for p in a.profiles:
        print(json.dumps({"profile": p, **micro(p)}))
        print(json.dumps(run_profile(p, a.workers)))


if __name__ == "__main__":
    from pcrcg.cli import one_line_errors

    with one_line_errors("pcrcg.benchmarks.data"):  # a bad file or setting: one line, exit 2
        main()
