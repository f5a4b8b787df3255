"""Which settings of a table's runs differ from the paper's text or from its official code.

Where the paper's text and the official code (Gardlin/PCR-CG, built on Predator) disagree, the
published numbers came from the code; the project offers both and defaults to the code. Each table of
the report says, from the logged params of the runs behind its cells, which of these settings its
runs used where they differ from the text, the code or both (:func:`fidelity_lines`): whether the 2D
network was detached, the RANSAC budget, the profile, the views' combination, the 2D net and its
BatchNorm statistics, the 2D matcher, what the Pri3D weights saw.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import pandas as pd


def _param(rec: Mapping, key: str) -> str | None:
    for col in (f"params.{key}", f"tags.{key}"):
        v = rec.get(col)
        if v is not None and not (isinstance(v, float) and v != v):
            return str(v)
    return None


def _deep(rec: Mapping) -> bool:
    return _param(rec, "features.name") == "deep" and _param(rec, "projection.name") in ("implicit", "explicit")


def _color(rec: Mapping) -> bool:
    return _param(rec, "features.name") not in (None, "none") and _param(rec, "projection.name") in ("implicit",
                                                                                                   "explicit")


def _learned(rec: Mapping) -> bool:
    return _param(rec, "method") in (None, "learned") or _param(rec, "icp_init") == "learned"


def _predator(rec: Mapping) -> bool:
    """A learned Predator-based run (GeoTransformer's settings are its own: its circle-loss scale is 24)."""
    return _learned(rec) and _param(rec, "model.name") in (None, "predator")


@dataclass(frozen=True)
class Setting:
    """One setting: its logged key, the value of the paper's text and of the official code (as logged
    text; None: the source does not say), words for values, which runs it concerns, and the value that
    runs logged before the setting existed ran with (None: such runs are left out)."""

    key: str
    name: str
    text: str | None
    code: str | None
    words: Mapping[str, str] = field(default_factory=dict)
    applies: Callable[[Mapping], bool] = lambda rec: True
    before: str | None = None

    def say(self, value: str | None) -> str:
        return self.words.get(str(value), f"{self.name} {value}")


SETTINGS: tuple[Setting, ...] = (
    Setting("profile", "profile", "paper", "official",
            {"paper": "profile paper (the paper's text: Predator's sizes, 30 epochs)",
             "official": "profile official (the official training config: 256/512 wide, 64-d, 150 epochs)",
             "cpu": "profile cpu (6 cm voxels, 3 levels, 32-wide first layer, 1,800 steps: a CPU-sized model)",
             "tiny": "profile tiny (a few training steps: the tests' size)"}),
    Setting("encoder2d.training", "2D network training", "end_to_end", "detached",
            {"detached": "the 2D network detached (not trained)", "end_to_end": "the 2D network trained end to end"},
            lambda r: _deep(r) and _learned(r)),
    Setting("registration.ransac.max_validation", "RANSAC validation budget", None, "1000",
            {"1000": "RANSAC stops after 1000 validated hypotheses (Open3D 0.10's criteria)",
             "null": "RANSAC with Open3D >= 0.12's budget (no validation cap, early exit)"}),
    Setting("registration.fewer_points", "small fragments", None, "with_replacement",
            {"with_replacement": "fragments with fewer than N points resampled with replacement",
             "whole": "fragments with fewer than N points used whole"}),
    Setting("model.loss.log_scale", "circle-loss scale", None, "16", {}, _predator),
    Setting("model.loss.matchability_after_recall", "matchability loss", None, "official",
            {"official": "the matchability loss as each official trainer (with 2D features: from the first step)",
             "0.3": "the matchability loss only after a validation feature recall above 0.3 (Predator's schedule; "
                    "PCR-CG's trainer has it from the first step)",
             "0.0": "the matchability loss from the first step (as PCR-CG's trainer)"},
            lambda r: _color(r) and _predator(r)),
    Setting("projection.combine", "several views", "mean", "overwrite",
            {"overwrite": "several views: the first that sees a point gives its feature",
             "mean": "several views: features averaged"}, lambda r: _color(r) and _learned(r)),
    Setting("projection.unseen_value", "feature of points no view sees", None, "1.0",
            {"1.0": "points no view sees get the constant 1", "0.0": "points no view sees get zeros"},
            lambda r: _color(r) and _learned(r)),
    Setting("projection.window_style", "explicit windows", "centred", "official",
            {"centred": "explicit windows of window_size x window_size pixels centred on the matches",
             "official": "explicit windows as the official code's slices (2 * ((window_size - 1) // 2) pixels wide, "
                         "later matches overwriting, none past the top or left border)"},
            lambda r: _color(r) and _learned(r) and _param(r, "projection.name") == "explicit", before="centred"),
    Setting("encoder2d.arch", "2D encoder", "resnet50", "resnet50", {}, lambda r: _deep(r) and _learned(r)),
    Setting("encoder2d.out_dim", "2D feature width", "128", "128", {}, lambda r: _deep(r) and _learned(r)),
    Setting("encoder2d.bn_stats", "2D BatchNorm statistics", None, "per_image",
            {"per_image": "2D BatchNorm normalising each image by its own statistics",
             "running": "2D BatchNorm with batch statistics in training and running averages at test"},
            lambda r: _deep(r) and _learned(r), before="running"),
    Setting("encoder2d.normalize", "2D input normalisation", None, "False",
            {"True": "2D input normalised (ImageNet mean/std)", "False": "2D input not normalised"},
            lambda r: _deep(r) and _learned(r)),
    Setting("matcher2d.method", "2D matcher", "superglue", "superglue",
            {"superglue": "SuperGlue's matches", "sift": "2D matches from SIFT", "orb": "2D matches from ORB", "lightglue": "2D matches from LightGlue"},
            lambda r: _color(r) and _param(r, "projection.name") == "explicit"),
    Setting("encoder2d.pretrained_on", "Pri3D pretrained on", "scannet", "scannet",
            {"scannet": "Pri3D's own weights (pretrained on ScanNet)"}, lambda r: _deep(r) and _learned(r) and _param(r, "encoder2d.name") == "pri3d"),
)

_WORDS = {"paper": "the paper's text", "code": "the official code"}


def _ref(s: Setting, which: str) -> str:
    value = s.text if which == "paper" else s.code
    return s.words.get(str(value), f"{s.name} {value}") if value is not None else ""


def fidelity_lines(runs: pd.DataFrame, settings: tuple[Setting, ...] = SETTINGS) -> list[str]:
    """One line per setting whose value in ``runs`` (the runs behind a table) differs from the paper's
    text or its official code: what the runs used (with run counts when they differ), then what the
    code and the text have."""
    if runs.empty:
        return []
    out = []
    recs = [rec for _, rec in runs.iterrows()]
    for s in settings:
        values = pd.Series([_param(r, s.key) or s.before for r in recs if s.applies(r)], dtype=object).dropna()
        if values.empty:
            continue
        counts = values.value_counts()
        differ = [v for v in counts.index if (s.code is not None and v != s.code) or (s.text is not None and v != s.text)]
        if not differ:
            continue
        used = "; ".join(s.say(v) + (f" ({n} runs)" if len(counts) > 1 else "") for v, n in counts.items())
        refs = []
        for which, ref in (("code", s.code), ("paper", s.text)):
            if ref is None:
                continue
            same = all(v == ref for v in counts.index)
            refs.append(f"as {_WORDS[which]}" if same else f"{_WORDS[which]}: {_ref(s, which)}")
        out.append(used + (f" ({', '.join(refs)})" if refs else ""))
    return out
