"""Make the Pri3D weights a run needs when they are missing (``encoder2d=pri3d encoder2d.make=true``).

The main, window and views tables use Pri3D weights (their captions say so), so their sweeps run
with ``encoder2d=pri3d``. Its default ``encoder2d.weights`` is where ``python -m pcrcg.pretrain2d``
writes for the run's profile and the pretraining data ``encoder2d.pretrained_on`` names; when that
file is missing, :func:`make_missing_weights` runs the pretraining once (a subprocess, under a file
lock, so the parallel jobs of a sweep wait for one pretraining) and the run goes on with the file.

Only generated pretraining data (``synthmatch-seed<N>``) are made this way; weights from real frames
(``pretrained_on=redkitchen``) or a file given in ``encoder2d.weights`` must exist (the run's
preflight names the file and the command that makes it).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable, Mapping

from pcrcg.errors import ConfigError, PcrcgError

_GENERATED = re.compile(r"^(?P<name>synthmatch)-seed(?P<seed>\d+)$")


def _value(v: Any) -> str:
    """A plain value as a Hydra override value."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_value(x) for x in v) + "]"
    return str(v)


def needs_weights(data: Mapping[str, Any]) -> bool:
    """Whether the run builds a Pri3D-initialised 2D encoder (learned color model with deep features)."""
    from pcrcg.config import color_enabled

    enc = data.get("encoder2d") if isinstance(data.get("encoder2d"), Mapping) else {}
    feats = data.get("features") if isinstance(data.get("features"), Mapping) else {}
    learned = data.get("method", "learned") == "learned" or data.get("icp_init") == "learned"
    return bool(learned and color_enabled(data) and feats.get("name") == "deep" and enc.get("name") == "pri3d")


def pretrain_overrides(data: Mapping[str, Any], weights: Path) -> list[str]:
    """The ``python -m pcrcg.pretrain2d`` overrides that write the run's Pri3D weights to ``weights``:
    the run's profile (and its ``profile.pretrain2d`` sizes), the data ``encoder2d.pretrained_on``
    names, the encoder's architecture and widths, the run's logger."""
    enc = dict(data["encoder2d"])
    tag = str(enc.get("pretrained_on") or "")
    m = _GENERATED.match(tag)
    if m is None:
        raise ConfigError("encoder2d.pretrained_on", tag,
                          "synthmatch-seed<N> to let the run make the weights (other data: run python -m pcrcg.pretrain2d "
                          "yourself and set encoder2d.weights)")
    seed = int(m.group("seed"))
    profile = data.get("profile") if isinstance(data.get("profile"), Mapping) else {}
    # a profile that shares another's data and pretraining (official: paper) makes that profile's weights
    out = [f"profile={profile.get('data_profile') or profile.get('name', 'cpu')}",
           f"data={'synthmatch' if seed == int(data.get('data_seed', 0) or 0) else 'synthmatch_pretrain'}",
           f"data_seed={seed}", f"out={weights}"]
    for key, v in (profile.get("pretrain2d") or {}).items():
        out.append(f"profile.pretrain2d.{key}={_value(v)}")
    for key in ("arch", "out_dim", "decoder_channels", "normalize", "output_scale"):
        if key in enc:
            out.append(f"encoder2d.{key}={_value(enc[key])}")
    paths = data.get("paths") if isinstance(data.get("paths"), Mapping) else {}
    if paths.get("checkpoints"):
        out.append(f"paths.checkpoints={paths['checkpoints']}")
    logger = data.get("logger") if isinstance(data.get("logger"), Mapping) else {}
    if logger.get("name") == "none":
        out.append("logger=none")
    elif logger.get("tracking_uri"):
        out.append(f"logger.tracking_uri={logger['tracking_uri']}")
    return out


def make_missing_weights(data: Mapping[str, Any], base_dir: str | Path, log: Callable[[str], None] = print,
                         run: Callable[..., Any] = subprocess.run, hydra_dir: str | Path | None = None) -> Path | None:
    """Run ``python -m pcrcg.pretrain2d`` for the run's missing default Pri3D weights; returns the file
    made, or None when nothing had to be made. ``data``: the run's resolved config (plain containers)."""
    if not needs_weights(data):
        return None
    enc = data["encoder2d"]
    if not enc.get("make", False) or not enc.get("weights"):
        return None
    weights = Path(str(enc["weights"])).expanduser()
    if not weights.is_absolute():
        weights = Path(base_dir) / weights
    if weights.is_file():
        return None
    from filelock import FileLock

    weights.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(str(weights) + ".lock"):
        if weights.is_file():  # another job of the sweep made it meanwhile
            return None
        cmd = [sys.executable, "-m", "pcrcg.pretrain2d", *pretrain_overrides(data, weights)]
        if hydra_dir is not None:
            cmd.append(f"hydra.run.dir={hydra_dir}")
        log(f"[run] the Pri3D weights {weights} are missing: making them ({' '.join(cmd[1:])})")
        proc = run(cmd, cwd=str(base_dir), stdout=subprocess.PIPE, text=True)
        lines = (proc.stdout or "").strip().splitlines()
        if proc.returncode != 0 or not weights.is_file():
            raise PcrcgError(f"the 2D pretraining that makes encoder2d.weights={weights} failed (exit status "
                             f"{proc.returncode}); run it alone: python {' '.join(cmd[1:])}")
        try:
            result = json.loads(lines[-1]) if lines else {}
        except json.JSONDecodeError:
            result = {}
        log(f"[run] made {weights}: held-out match accuracy {result.get('match_acc_scratch')} -> "
            f"{result.get('match_acc_pretrained')} (pretrained on {result.get('pretrained_on', enc.get('pretrained_on'))})")
    return weights
