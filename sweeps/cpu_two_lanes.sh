#!/usr/bin/env bash
# Every paper table at the cpu profile on a 2-core machine, as two single-core lanes.
#
#   sweeps/cpu_two_lanes.sh                       # every table's jobs, both lanes in the background, then the report
#   sweeps/cpu_two_lanes.sh window_size views     # only these tables' jobs
#   DRY_RUN=1 sweeps/cpu_two_lanes.sh             # print the commands, run nothing
#
# The jobs are read from the experiment files (`python -m pcrcg.experiments --jobs`: every combination of
# each table's sweep axes, in sweeps/all_tables.sh's order), one job per `pcrcg.run +experiment=<table>
# key=value -m`, in one queue that two lanes take from, each the next job as soon as it is free, so that
# both cores stay busy (a table's jobs differ a lot in length: geometry-only ~25 min, PCR-CG ~45 min, a job
# that reuses a trained checkpoint ~25 min of evaluation; joblib would wait for the slowest job of each
# table). Each lane runs its jobs one after another with one torch thread; both lanes write to one MLflow store and share checkpoints (a lane that
# needs a model the other lane is training waits on its lock; the Pri3D weights are made on demand, once).
# Relaunching runs only what is missing. SEEDS="0,1,2" adds seed=0,1,2 to every job. LANES=1: one lane
# (the jobs one after another), for a machine with one core free. ONLY=REGEX: only the matching jobs.
set -u
cd "$(dirname "$0")/.."
LOGS=${LOGS:-outputs/lanes}
export MLFLOW_TRACKING_URI=${MLFLOW_TRACKING_URI:-sqlite:///$PWD/mlflow.db}
SEEDS=${SEEDS:-}
COMMON="profile=cpu runtime.report_on_end=false${SEEDS:+ seed=$SEEDS}"

# job, lane, two_lanes, run (DRY_RUN=1 prints the commands)
# shellcheck source=sweeps/lib.sh
. sweeps/lib.sh

mapfile -t JOBS < <("$PYTHON" -m pcrcg.experiments --jobs "$@") || exit 2
[ "${#JOBS[@]}" -gt 0 ] || { echo "cpu_two_lanes.sh: no jobs (python -m pcrcg.experiments --jobs $*)" >&2; exit 2; }
filter_jobs || exit 2
two_lanes || exit $?
run "$PYTHON" -m pcrcg.report profile=cpu
[ "$DRY_RUN" = 1 ] || echo "Tables: reports/README.md    Runs: mlflow ui --backend-store-uri $MLFLOW_TRACKING_URI"
