# Shared by the sweep scripts (source it): one job of a lane, logged, or printed with DRY_RUN=1.
#
#   PYTHON   the interpreter (default .venv/bin/python)
#   COMMON   overrides added to every job (e.g. "profile=cpu runtime.report_on_end=false")
#   DRY_RUN  1: print each command instead of running it (nothing is written)

PYTHON=${PYTHON:-.venv/bin/python}
DRY_RUN=${DRY_RUN:-0}

job() {  # job <lane log> <experiment> [overrides...]: one sweep (-m) of an experiment, appended to the lane's log
  local log=$1 exp=$2
  shift 2
  if [ "$DRY_RUN" = 1 ]; then
    echo "$PYTHON -m pcrcg.run +experiment=$exp $COMMON $* -m"
    return 0
  fi
  local start rc
  start=$(date +%s)
  echo "== $(date +%T) $exp $*" >>"$log"
  # shellcheck disable=SC2086  # COMMON is a list of overrides
  "$PYTHON" -m pcrcg.run +experiment="$exp" $COMMON "$@" -m >>"$log.out" 2>&1
  rc=$?
  echo "== $(date +%T) $exp $* -> rc $rc in $(( $(date +%s) - start )) s" >>"$log"
}

step() {  # step <lane log> <command...>: any other command of a lane (pretrain, evaluate, report), logged
  local log=$1
  shift
  if [ "$DRY_RUN" = 1 ]; then
    echo "$*"
    return 0
  fi
  local start rc
  start=$(date +%s)
  echo "== $(date +%T) $*" >>"$log"
  "$@" >>"$log.out" 2>&1
  rc=$?
  echo "== $(date +%T) $* -> rc $rc in $(( $(date +%s) - start )) s" >>"$log"
  return $rc
}

run() {  # run <command...>: in the foreground (output to the terminal), or printed with DRY_RUN=1
  if [ "$DRY_RUN" = 1 ]; then
    echo "$*"
    return 0
  fi
  "$@"
}

lane() {  # lane <n> [lanes]: every lanes-th job of the array JOBS ("<experiment> [overrides...]" each), from
  local k=$(( $1 - 1 )) of=${2:-2} L=$LOGS/lane$1.log   # job n, logged to $LOGS/lane<n>.log
  while [ "$k" -lt "${#JOBS[@]}" ]; do
    # shellcheck disable=SC2086  # "<experiment> [overrides...]"
    job "$L" ${JOBS[$k]}
    k=$(( k + of ))
  done
}

two_lanes() {  # the jobs of JOBS as LANES (default 2) single-core lanes at once; LANES=1: one after another
  local n lanes=${LANES:-2}   # (a core busy with other work); printed one lane after the other with DRY_RUN=1
  case $lanes in 1|2) ;; *) echo "LANES=$lanes: 1 or 2 (single-core lanes at once)" >&2; return 2 ;; esac
  if [ "$DRY_RUN" = 1 ]; then
    for n in $(seq 1 "$lanes"); do echo "# lane $n"; lane "$n" "$lanes"; done
    return 0
  fi
  mkdir -p "$LOGS"
  # a brand-new SQLite store is created once, before the lanes write to it at once
  "$PYTHON" -c "import mlflow; mlflow.MlflowClient('$MLFLOW_TRACKING_URI').search_experiments()" >/dev/null 2>&1
  local pids=()
  for n in $(seq 1 "$lanes"); do lane "$n" "$lanes" & pids+=("$!"); done
  wait "${pids[@]}"
}
