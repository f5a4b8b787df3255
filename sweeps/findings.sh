#!/usr/bin/env bash
# The sweep of record of the findings table (reports/findings.md): exactly the configs that the
# `findings` of conf/report.yaml select, every seed of `findings.seeds` (0,1,2), as two single-core
# lanes (as sweeps/cpu_two_lanes.sh), then every model of it on the real redkitchen scene, then the report.
#
#   sweeps/findings.sh [profile]          # profile: cpu (default) | tiny | paper
#   DRY_RUN=1 sweeps/findings.sh cpu      # print the commands, run nothing
#   python -m pcrcg.report.progress       # what a relaunch would skip and run (read from the store), the time left
#   LANES=1 sweeps/findings.sh cpu        # one lane: the jobs one after another (one core free)
#   ONLY=^main_results sweeps/findings.sh # only the jobs that match this extended regex (finding 1 first)
#   OUT=DIR sweeps/findings.sh            # where the report goes (default reports/findings-<profile>/)
#   REGISTRATION=inlier_ranking sweeps/findings.sh   # every job registers with that group of conf/registration/
#                                         # (RANSAC ranked by inlier correspondences, not the paper's overlap);
#                                         # the report selects those runs; default report reports/findings-<profile>-<group>/
#
# The job list comes from the findings spec (`python -m pcrcg.report.findings --jobs`: the claims' rows, then
# the targets'), so a finding or target added to conf/report.yaml is swept here. Resumable: a run skips
# its config when a FINISHED run of the same config and code exists, so relaunching (after a crash, over
# several sittings) runs only what is missing; the lanes share trained models (checkpoints/, under a file
# lock) and one MLflow store.
# The jobs run seed by seed (every job with seed=0, then seed=1, ...), each in the spec's order; each lane
# takes the next one as soon as it is free (the cpu profile trains with one torch thread).
set -u
cd "$(dirname "$0")/.."
PROFILE=${1:-cpu}
REGISTRATION=${REGISTRATION:-}
SUFFIX=${REGISTRATION:+-$REGISTRATION}
LOGS=${LOGS:-outputs/findings-$PROFILE$SUFFIX}
export MLFLOW_TRACKING_URI=${MLFLOW_TRACKING_URI:-sqlite:///$PWD/mlflow.db}
# shellcheck source=sweeps/lib.sh
. sweeps/lib.sh
REAL_ROOT=${REAL_ROOT:-data/real-redkitchen}
OUT=${OUT:-reports/findings-$PROFILE$SUFFIX}
SHARED=${SHARED:-../shared/data}

SEEDS=$("$PYTHON" -m pcrcg.report.findings --seeds) || exit 2
REG_ARGS=()
[ -n "$REGISTRATION" ] && REG_ARGS=(--registration "$REGISTRATION")
# the report's filters for the runs of that registration group (none: the report's own, the paper's protocol)
REPORT_WHERE=$("$PYTHON" -m pcrcg.report.findings --report-overrides "${REG_ARGS[@]}") || exit 2
mapfile -t REPORT_ARGS <<<"$REPORT_WHERE"
[ -n "$REPORT_WHERE" ] || REPORT_ARGS=()
mapfile -t JOBS < <("$PYTHON" -m pcrcg.report.findings --jobs "${REG_ARGS[@]}")
if [ "${#JOBS[@]}" -eq 0 ]; then
  echo "findings.sh: conf/report.yaml defines no findings (findings.claims)" >&2
  exit 2
fi
filter_jobs || exit 2
check_lanes || exit 2   # before the real scene is built
# the experiments of the jobs this sweep runs (all of the findings', or those ONLY keeps), in the spec's order
EXPERIMENTS=$(for j in "${JOBS[@]}"; do echo "${j%% *}"; done | awk '!seen[$0]++' | paste -sd, -)
# seed by seed: every job of seed 0, then of seed 1, ...: a sweep stopped half way has whole seeds of
# every row it reached, so its findings already compare like with like
if [ -n "$SEEDS" ]; then
  BASE=("${JOBS[@]}")
  JOBS=()
  for s in ${SEEDS//,/ }; do
    for j in "${BASE[@]}"; do JOBS+=("$j seed=$s"); done
  done
fi
COMMON="profile=$PROFILE runtime.report_on_end=false"

# the real scene: built once from ../shared/data (when it is here) before the lanes; each lane evaluates every
# model of an experiment the findings read on it right after a job of that experiment (`after_job`), while its
# checkpoint is still on this machine (a machine that is shut down keeps the store, not checkpoints/), and
# every run of them once more after the lanes (what a crash left out)
L=$LOGS/real.log
REAL_EXPERIMENTS=""
if [ -d "$SHARED" ]; then
  [ "$DRY_RUN" = 1 ] || mkdir -p "$LOGS"
  if [ ! -f "$REAL_ROOT/manifest.json" ]; then
    step "$L" "$PYTHON" -m pcrcg.prepare data=threedmatch data.source.fragments_dir="$SHARED/real-3dmatch-fragments" \
      data.source.rgbd_dir="$SHARED/real-rgbd" data.root="$REAL_ROOT"
  fi
  # those the findings read on the real scene (`--real-experiments`: the claims', and a target's whose
  # benchmark is the real scene's; FPFH + RANSAC for the generated-3DMatch target is not among them)
  REAL_EXPERIMENTS=",$("$PYTHON" -m pcrcg.report.findings --real-experiments),"
else
  echo "findings.sh: $SHARED is not here: no real-scene evaluation (the findings show — in its columns)" >&2
fi

real_eval() {  # real_eval <log> <experiment>: the experiment's finished runs not yet on the real scene, evaluated
  [[ $REAL_EXPERIMENTS == *",$2,"* ]] || return 0   # on it (one lane at a time: the other then skips them)
  [ "$DRY_RUN" = 1 ] || [ -f "$REAL_ROOT/manifest.json" ] || return 0
  step "$1" flock "$LOGS/real.lock" "$PYTHON" -m pcrcg.evaluate mode=tracked "experiments=[$2]" \
    data.root="$REAL_ROOT" name=real-redkitchen profile="$PROFILE"
}
after_job() { real_eval "$1" "$2"; }

two_lanes || exit $?
unset -f after_job

# one experiment at a time: one whose runs all failed (or are not in the store) does not stop the others
for e in ${EXPERIMENTS//,/ }; do
  real_eval "$L" "$e"
done
# the report of this sweep alone: the findings and the tables of its experiments, in their own folder (the
# tables of reports/ may come from other sweeps and stores)
run "$PYTHON" -m pcrcg.report profile="$PROFILE" "tables=[$EXPERIMENTS]" out_dir="$OUT" "${REPORT_ARGS[@]}"
[ "$DRY_RUN" = 1 ] || echo "Findings: $OUT/findings.md    Runs: mlflow ui --backend-store-uri $MLFLOW_TRACKING_URI"
