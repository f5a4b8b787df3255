#!/usr/bin/env bash
# Regenerate every paper table in one go: one sweep per table, then the report.
#
#   sweeps/all_tables.sh [profile] [overrides...]
#   sweeps/all_tables.sh cpu                                   # this laptop, one job at a time
#   sweeps/all_tables.sh cpu hydra/launcher=joblib2            # two jobs at a time
#   sweeps/all_tables.sh paper seed=0,1,2 hydra/launcher=slurm hydra.launcher.partition=gpu
#
# Relaunching it runs only what is missing: a job whose config hash already has a FINISHED run
# is skipped, a crashed training resumes from its last checkpoint. The order lets later tables
# reuse trained models (same training config -> same checkpoint): main_results trains Predator and
# PCR-CG (Pri3D weights, explicit, 2 views, 11x11, 2D net detached; the first run that needs the Pri3D
# weights makes them); ransac_budget, window_size 11, views_explicit 2, backbone_2d's Pri3D/detached row
# and icp_init's improved pose reuse PCR-CG's checkpoint (views is implicit: its own trainings).
set -u
PYTHON=${PYTHON:-python}
PROFILE=${1:-cpu}
shift || true
# the tables in their order (pcrcg.experiments.TABLE_ORDER)
EXPERIMENTS=${EXPERIMENTS:-$("$PYTHON" -m pcrcg.experiments --experiments | tr '\n' ' ')}

status=0
for exp in $EXPERIMENTS; do
  echo "== $exp (profile $PROFILE) =="
  start=$(date +%s)
  "$PYTHON" -m pcrcg.run +experiment="$exp" profile="$PROFILE" runtime.report_on_end=false "$@" -m || status=1
  echo "== $exp: $(( $(date +%s) - start )) s =="
done
"$PYTHON" -m pcrcg.report profile="$PROFILE" || status=1
echo "Tables: reports/README.md    Runs: mlflow ui --backend-store-uri ${MLFLOW_TRACKING_URI:-sqlite:///mlflow.db}"
exit $status
