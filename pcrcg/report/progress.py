"""How far the findings sweep has got in a store, and what is left: ``python -m pcrcg.report.progress``.

    python -m pcrcg.report.progress [--profile cpu] [--registration inlier_ranking] [--tracking-uri URI]
        [--lanes 2] [--config conf/report.yaml]

The sweep of record (``sweeps/findings.sh``) spans several sittings: it runs the findings spec's jobs
(``python -m pcrcg.report.findings --jobs``) for every seed, seed by seed, and a relaunch skips every job whose
config already FINISHED with this code. This command says, without running or writing anything, what such a
relaunch would skip and what it would run. For every job and seed it composes the job's config as ``python -m
pcrcg.run +experiment=<experiment> profile=<profile> <overrides> seed=<seed> -m`` does (the experiment's
``hydra.sweeper.params`` that the job leaves open expand into one job per value, as Hydra's basic sweeper
does), hashes it as a run does (:func:`pcrcg.pipeline.run_hash`) and looks the hash up in the store:

* ``finished``: a FINISHED run of that hash with this checkout's code version (:func:`pcrcg.tracking.git.code_version`;
  ``--code-version V``: the sweep's, when it runs from another checkout whose result code differs);
* ``running``: a RUNNING one with this code version whose process is alive (or runs on another host);
* ``stale``: RUNNING with this code version, but its process on this host is gone (a lane killed, a session
  ended; :func:`pcrcg.tracking.tracker.is_stale`): a relaunch closes it as KILLED and runs the job again;
* ``older code``: FINISHED only with another code version (a relaunch runs it again);
* ``to run``: none;
* ``same as #k``: the config of an earlier run of the list in the same experiment (a seedless method, e.g. ICP
  from the identity or FPFH: the sweep runs it once and skips it at the other seeds).

A finished run's CPU time (``time/total_cpu_s``, logged since 2026-12-05: :class:`pcrcg.pipeline.Clock`) is what it
cost on a core of its own; its wall time adds the time it waited for a core beside the other lanes. A run whose
training resumed from a checkpoint counts what its earlier starts spent up to that checkpoint
(:func:`pcrcg.pipeline.run_seconds`; logged since 2026-12-08).
The time left is the sum, over the jobs not finished, of the median wall time (``time/total_s``) of the finished
runs of the same job at other seeds (else of the experiment's), divided by ``--lanes``; a job with neither is
counted apart. Read-only: the store is opened, never written.
"""

from __future__ import annotations

import argparse
import itertools
import re
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from pcrcg.errors import ConfigError, PcrcgError

STATES = ("finished", "running", "stale", "older code", "to run", "same as")


@dataclass
class JobState:
    """One job of the sweep: its command's overrides, what the store holds for it and its wall time (s, a
    finished run's own, else an estimate from others; None: no estimate)."""

    experiment: str
    overrides: tuple[str, ...]
    seed: int
    config_hash: str
    state: str
    seconds: float | None = None
    run_id: str | None = None
    store_experiment: str = ""  # the MLflow experiment its runs go to (the config's experiment_name)
    real: str = ""  # a finished run the findings read on the real scene: "yes" when it has its metrics, else "no"
    cpu_seconds: float | None = None  # a finished run's CPU seconds (``time/total_cpu_s``; None: its code did not log it)

    @property
    def label(self) -> str:
        return " ".join([self.experiment, *self.overrides])


def sweeper_expansion(overrides: Sequence[str], sweeper_params: Mapping[str, Any] | None) -> list[list[str]]:
    """The jobs a multirun makes of ``overrides``: one per combination of the experiment's
    ``hydra.sweeper.params`` values (comma-separated) whose keys the overrides leave open, in Hydra's basic
    sweeper's order (the first key varies slowest). Keys set by an override (``key=...``, ``+key=...``) are
    not expanded."""
    fixed = {o.split("=", 1)[0].lstrip("+~") for o in overrides if "=" in o}
    open_keys = [(k, [v.strip() for v in str(vals).split(",")]) for k, vals in (sweeper_params or {}).items()
                 if k not in fixed]
    if not open_keys:
        return [list(overrides)]
    return [list(overrides) + [f"{k}={v}" for (k, _), v in zip(open_keys, combo)]
            for combo in itertools.product(*(vals for _, vals in open_keys))]


def compose_job(overrides: Sequence[str], config_dir: str | Path | None = None) -> tuple[Any, dict[str, Any]]:
    """The run config of ``python -m pcrcg.run <overrides>`` (without the ``hydra`` node) and its experiment's
    ``hydra.sweeper.params``."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf, open_dict

    from pcrcg.config import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(Path(config_dir or CONF_DIR).resolve()), version_base="1.3"):
        cfg = compose(config_name="run", overrides=list(overrides), return_hydra_config=True)
    params = OmegaConf.to_container(cfg.hydra.sweeper.params) if cfg.hydra.sweeper.get("params") else {}
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg, dict(params or {})


def expand_jobs(jobs: Iterable[tuple[str, str]], seeds: Sequence[int], profile: str,
                config_dir: str | Path | None = None, extra: Sequence[str] = ()) -> list[tuple[str, list[str], int, Any]]:
    """``(experiment, overrides, seed, config)`` of every run the sweep makes: seed by seed, each job in order
    (as ``sweeps/findings.sh``), a job's open sweeper keys expanded (:func:`sweeper_expansion`); ``extra``:
    overrides of every job (e.g. the sweep's stages)."""
    out = []
    for seed in seeds:
        for exp, job in jobs:
            base = [f"+experiment={exp}", f"profile={profile}", *job.split(), *extra, f"seed={seed}"]
            cfg, params = compose_job(base, config_dir)
            expanded = sweeper_expansion(base, params)
            for ov in expanded:
                out.append((exp, ov[2:], seed, cfg if ov == base else compose_job(ov, config_dir)[0]))
    return out


def _store_runs(uri: str, experiments: Iterable[str]) -> dict[str, list[dict[str, Any]]]:
    """Per experiment name, its runs: ``{"id", "hash", "code", "status", "seconds", "cpu", "name", "stale", "data"}``
    (read-only; ``stale``: RUNNING, and its process on this host is gone; ``data``: the prefixes of its metrics
    ``<name>/...``, e.g. the real scene's, that ``pcrcg.evaluate mode=tracked name=<name>`` logged)."""
    from pcrcg.pipeline import run_seconds
    from pcrcg.tracking.store import client, require_store
    from pcrcg.tracking.tracker import TAG_CODE, TAG_HASH, is_stale

    require_store(uri)
    c = client(uri)
    out: dict[str, list[dict[str, Any]]] = {}
    for name in dict.fromkeys(experiments):
        exp = c.get_experiment_by_name(name)
        runs = c.search_runs([exp.experiment_id], max_results=50000) if exp is not None else []
        out[name] = [{"id": r.info.run_id, "hash": r.data.tags.get(TAG_HASH), "code": r.data.tags.get(TAG_CODE),
                      "status": r.info.status, "seconds": run_seconds(r.data.metrics),
                      "cpu": run_seconds(r.data.metrics, cpu=True),
                      "name": r.info.run_name or "", "stale": is_stale(r.info.status, r.data.tags),
                      "data": {k.split("/", 1)[0] for k in r.data.metrics if "/" in k}}
                     for r in runs]
    return out


def job_states(planned: Sequence[tuple[str, list[str], int, Any]], runs: Mapping[str, list[dict[str, Any]]],
               code: str, reference: Mapping[str, list[dict[str, Any]]] | None = None, real: str | None = None,
               real_experiments: Iterable[str] = ()) -> list[JobState]:
    """What the store (``runs``, per experiment name: :func:`_store_runs`) holds for each planned run
    (:data:`STATES`), with the wall time of a finished one, and for the others an estimate (:func:`_estimate`, from
    ``runs`` and the ``reference`` store's runs). ``real``: the real data set's metric prefix; a finished run of
    ``real_experiments`` says whether it has been evaluated there. A run's hash is looked up as this checkout
    hashes it and as code before aa220c7 did (2D weights by the file's bytes: :func:`pcrcg.pipeline.run_hash`
    ``weights_by_bytes``), so that a sweep of an older code version (``--code-version``) is read right."""
    from pcrcg.pipeline import run_hash
    from pcrcg.tracking.hashing import to_plain

    on_real = set(real_experiments) if real else set()
    states: list[JobState] = []
    first: dict[tuple[str, str], int] = {}
    for exp, ov, seed, cfg in planned:
        plain = to_plain(cfg)
        h = run_hash(plain)
        hashes = {h, run_hash(plain, weights_by_bytes=True)}
        overrides = tuple(o for o in ov if not o.startswith(("profile=", "seed=")))
        name = str(cfg.experiment_name)
        key = (name, h)  # a run skips only runs of its own experiment
        if key in first:  # the same config again (a seedless method): one run for all
            states.append(JobState(exp, overrides, seed, h, f"same as #{first[key] + 1}", store_experiment=name))
            continue
        first[key] = len(states)
        mine = [r for r in runs.get(name, []) if r["hash"] in hashes]
        done = [r for r in mine if r["status"] == "FINISHED" and r["code"] == code]
        if done:
            state, r = "finished", done[0]
        elif any(r["status"] == "RUNNING" and r["code"] == code and not r.get("stale") for r in mine):
            state, r = "running", None
        elif any(r["status"] == "RUNNING" and r["code"] == code for r in mine):
            state, r = "stale", None
        elif any(r["status"] == "FINISHED" for r in mine):
            state, r = "older code", None
        else:
            state, r = "to run", None
        seen = ("yes" if real in r.get("data", ()) else "no") if r and exp in on_real else ""
        states.append(JobState(exp, overrides, seed, h, state, r["seconds"] if r else None, r["id"] if r else None,
                               store_experiment=name, real=seen, cpu_seconds=r.get("cpu") if r else None))
    merged = {k: [*runs.get(k, []), *(reference or {}).get(k, [])] for k in {*runs, *(reference or {})}}
    _estimate(states, merged)
    return states


def _estimate(states: list[JobState], runs: Mapping[str, list[dict[str, Any]]]) -> None:
    """Fills ``seconds`` of the jobs not finished: the median wall time of the same job's finished runs (other
    seeds of this sweep), else of the store's finished runs of the same name but for the seed (any code), else of
    every finished run of the experiment."""
    by_job: dict[tuple[str, tuple[str, ...]], list[float]] = {}
    for s in states:
        if s.state == "finished" and s.seconds is not None:
            by_job.setdefault((s.experiment, s.overrides), []).append(s.seconds)
    for s in states:
        if s.state == "finished" or s.state.startswith("same as"):
            continue
        done = [r for r in runs.get(s.store_experiment, []) if r["status"] == "FINISHED" and r["seconds"]]
        named = [r["seconds"] for r in done
                 if re.sub(r"(^| )seed=\d+", "", r["name"]).strip() == " ".join(s.overrides)]
        same = by_job.get((s.experiment, s.overrides)) or named or [r["seconds"] for r in done]
        s.seconds = statistics.median(same) if same else None


def _hms(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    m = int(round(seconds / 60))
    return f"{m // 60} h {m % 60:02d} min" if m >= 60 else f"{m} min"


def _cpu_total(states: Sequence[JobState]) -> str:
    """`` CPU time: ...`` of the finished runs that logged it (what they cost on cores of their own), else ''."""
    done = [s for s in states if s.state == "finished"]
    cpu = [s.cpu_seconds for s in done if s.cpu_seconds is not None]
    return (f" CPU time: {_hms(sum(cpu))} in all ({len(cpu)} of the {len(done)} finished runs logged it: "
            "code from 2026-12-05 on)") if cpu else ""


def render(states: Sequence[JobState], lanes: int, code: str, uri: str) -> str:
    """The progress table (one line per run, in the sweep's order) and the totals."""
    lines = [f"Store {uri}, code version {code}: the findings sweep, {len(states)} runs", "",
             "| # | seed | job | state | wall time | CPU time | real scene |", "|---:|---:|---|---|---:|---:|---|"]
    for k, s in enumerate(states, 1):
        t = (_hms(s.seconds) if s.state == "finished" else "–" if s.state.startswith("same as")
             else f"~{_hms(s.seconds)}" if s.seconds else "?")
        cpu = _hms(s.cpu_seconds) if s.state == "finished" and s.cpu_seconds is not None else "–"
        lines.append(f"| {k} | {s.seed} | {s.label} | {s.state} | {t} | {cpu} | {s.real or '–'} |")
    counts = {st: sum(s.state.startswith(st) for s in states) for st in STATES}
    left = [s for s in states if s.state not in ("finished",) and not s.state.startswith("same as")]
    known = [s.seconds for s in left if s.seconds is not None]
    done_s = sum(s.seconds or 0.0 for s in states if s.state == "finished")
    lines += ["", ", ".join(f"{n} {st}" for st, n in counts.items()) + ".",
              f"Finished runs' wall time: {_hms(done_s)} in all." + _cpu_total(states),
              (f"Left: {len(left)} runs, ~{_hms(sum(known))} of run time ({len(left) - len(known)} without an "
               f"estimate), ~{_hms(sum(known) / max(lanes, 1))} of wall time on {lanes} lane(s)." if known else
               f"Left: {len(left)} runs, none with an estimate yet (no finished run of their jobs here; "
               "`--estimates-from URI`: another store's runs of the same jobs).")]
    missing = [k for k, s in enumerate(states, 1) if s.real == "no"]
    if missing:
        lines.append(f"Finished but not on the real scene: {', '.join(f'#{k}' for k in missing)} (the sweep evaluates "
                     "them after their job; `python -m pcrcg.evaluate mode=tracked` names a run whose checkpoint is "
                     "gone, with the command that trains it again).")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m pcrcg.report.progress",
                                description="How far the findings sweep has got in a store, and what is left "
                                            "(read-only).")
    p.add_argument("--profile", default="cpu")
    p.add_argument("--registration", default=None,
                   help="the sweep's registration group (sweeps/findings.sh's REGISTRATION), e.g. inlier_ranking")
    p.add_argument("--tracking-uri", default=None, help="the store (default: MLFLOW_TRACKING_URI, else sqlite:///mlflow.db)")
    p.add_argument("--lanes", type=int, default=2, help="lanes for the wall-time estimate (default 2)")
    p.add_argument("--estimates-from", default=None, metavar="URI",
                   help="another store whose finished runs also serve the time estimates (e.g. an earlier sweep's)")
    p.add_argument("--code-version", default=None,
                   help="the code version the sweep runs (default: this checkout's; a sweep run from another checkout "
                        "whose result code differs is told by its runs' code_version tag)")
    p.add_argument("--config", default=None, help="a report config (default: conf/report.yaml)")
    args = p.parse_args(argv)
    from pcrcg.report.findings import load_findings, registration_where
    from pcrcg.tracking.git import code_version
    from pcrcg.tracking.store import require_store, resolve_tracking_uri

    try:
        where = registration_where(args.registration) if args.registration else {}
        spec = load_findings(args.config, where)
        if spec is None:
            raise ConfigError("findings", None, "claims in conf/report.yaml (findings.claims)")
        uri = resolve_tracking_uri(args.tracking_uri)
        require_store(uri)
        if args.estimates_from:
            require_store(resolve_tracking_uri(args.estimates_from))
        planned = expand_jobs(spec.jobs(), spec.seeds, args.profile)
        names = {str(cfg.experiment_name) for *_, cfg in planned}
        runs = _store_runs(uri, names)
        ref = _store_runs(resolve_tracking_uri(args.estimates_from), names) if args.estimates_from else {}
        code = args.code_version or code_version()
        print(render(job_states(planned, runs, code, ref, spec.real, spec.real_experiments), args.lanes, code, uri))
    except PcrcgError as e:
        print(f"python -m pcrcg.report.progress: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
