#!/usr/bin/env bash
# Every paper table at the cpu profile on a 2-core machine, as two single-core lanes.
#
#   sweeps/cpu_two_lanes.sh            # both lanes in the background, then the report
#   DRY_RUN=1 sweeps/cpu_two_lanes.sh  # print the commands, run nothing
#
# The same jobs as `sweeps/all_tables.sh cpu hydra/launcher=joblib2`, split by hand so that both
# cores stay busy: a table's sweep holds jobs of very different lengths (geometry-only ~6 min,
# PCR-CG ~14 min, a job that reuses a trained checkpoint ~4 min), and joblib waits for the
# slowest job of each table before starting the next table. Each lane runs its jobs one after
# another with one torch thread; both lanes write to one MLflow store (created here first) and
# share checkpoints (a lane that needs a model the other lane is training waits on its lock).
# Command-line values override an experiment's sweep axis, so `+experiment=window_size
# window_size=3 -m` is one job of that table. Relaunching runs only what is missing.
set -u
cd "$(dirname "$0")/.."
LOGS=${LOGS:-outputs/lanes}
[ "${DRY_RUN:-0}" = 1 ] || mkdir -p "$LOGS"
export MLFLOW_TRACKING_URI=${MLFLOW_TRACKING_URI:-sqlite:///$PWD/mlflow.db}
COMMON="profile=cpu runtime.report_on_end=false"

# job <lane log> <experiment> [overrides...] and step <lane log> <command...> (DRY_RUN=1 prints them)
# shellcheck source=sweeps/lib.sh
. sweeps/lib.sh

lane1() {
  local L=$LOGS/lane1.log
  job "$L" main_results features=deep
  job "$L" window_size window_size=3
  job "$L" window_size window_size=7
  job "$L" views views=1
  job "$L" projection features=deep projection=implicit
  job "$L" projection features=rgb projection=explicit
  job "$L" projection features=rgb projection=implicit
  job "$L" window_size window_size=11
  job "$L" icp_init
}

lane2() {
  local L=$LOGS/lane2.log
  job "$L" main_results features=none
  job "$L" sift_dlt
  step "$L" "$PYTHON" -m pcrcg.pretrain2d profile=cpu
  job "$L" backbone_2d
  job "$L" window_size window_size=17
  job "$L" views views=3
  job "$L" projection features=sift projection=explicit
  job "$L" projection features=sift projection=implicit
  job "$L" views views=2
  job "$L" projection features=deep projection=explicit
}

# a brand-new SQLite store is created once, before the lanes write to it at once
if [ "$DRY_RUN" = 1 ]; then
  lane1; lane2
else
  "$PYTHON" -c "import mlflow; mlflow.MlflowClient('$MLFLOW_TRACKING_URI').search_experiments()" >/dev/null 2>&1
  lane1 & p1=$!
  lane2 & p2=$!
  wait $p1 $p2
fi
run "$PYTHON" -m pcrcg.report profile=cpu
[ "$DRY_RUN" = 1 ] || echo "Tables: reports/README.md    Runs: mlflow ui --backend-store-uri $MLFLOW_TRACKING_URI"
