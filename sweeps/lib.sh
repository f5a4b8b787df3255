# Shared by the sweep scripts (source it): one job of a lane, logged, or printed with DRY_RUN=1.
#
#   PYTHON   the interpreter (default .venv/bin/python)
#   COMMON   overrides added to every job (e.g. "profile=cpu runtime.report_on_end=false")
#   DRY_RUN  1: print each command instead of running it (nothing is written)
#   LANES    1 or 2 (default): single-core lanes at once, fed from one queue
#   ONLY     an extended regex: only the jobs ("<experiment> [overrides...]") that match it

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

next_job() {  # next_job: the index of the next job of JOBS that no lane has taken yet (the shared queue
  local n                      # $QUEUE, a counter under a file lock); fails when every job is taken
  exec 9>>"$QUEUE.lock"
  flock 9
  n=$(cat "$QUEUE" 2>/dev/null || echo 0)
  echo $(( n + 1 )) >"$QUEUE"
  flock -u 9
  exec 9>&-
  [ "$n" -lt "${#JOBS[@]}" ] && echo "$n"
}

lane() {  # lane <n>: takes the next job of the array JOBS ("<experiment> [overrides...]" each) from the shared
  local k L=$LOGS/lane$1.log   # queue as long as one is left, logged to $LOGS/lane<n>.log; after each job, the
  while k=$(next_job); do      # script's own `after_job <lane log> <experiment> [overrides...]` if it has one
    # shellcheck disable=SC2086  # "<experiment> [overrides...]"
    job "$L" ${JOBS[$k]}
    if [ "$DRY_RUN" != 1 ] && declare -F after_job >/dev/null; then
      # shellcheck disable=SC2086
      after_job "$L" ${JOBS[$k]}
    fi
  done
}

filter_jobs() {  # filter_jobs: keeps the jobs of JOBS that match the extended regex $ONLY (when set); fails
  [ -n "${ONLY:-}" ] || return 0   # (one line to stderr) when none does
  local kept=() j
  for j in "${JOBS[@]}"; do [[ $j =~ $ONLY ]] && kept+=("$j"); done
  if [ "${#kept[@]}" -eq 0 ]; then
    echo "ONLY=$ONLY matches no job (of ${#JOBS[@]}: ${JOBS[0]} ...)" >&2
    return 2
  fi
  JOBS=("${kept[@]}")
}

check_lanes() {  # check_lanes: fails (one line to stderr) unless LANES is 1 or 2 (default 2)
  case ${LANES:-2} in 1|2) ;; *) echo "LANES=$LANES: 1 or 2 (single-core lanes at once)" >&2; return 2 ;; esac
}

two_lanes() {  # the jobs of JOBS on LANES (default 2) single-core lanes at once: each lane takes the next job in
  local n lanes=${LANES:-2}   # order as soon as it is free (jobs differ a lot in length); LANES=1: one after another
  check_lanes || return 2
  if [ "$DRY_RUN" = 1 ]; then
    echo "# queue: $lanes lane(s), each takes the next job when it is free"
    local j
    # shellcheck disable=SC2086  # "<experiment> [overrides...]"
    for j in "${JOBS[@]}"; do job - $j; done
    return 0
  fi
  mkdir -p "$LOGS"
  QUEUE=$LOGS/queue.$$
  echo 0 >"$QUEUE"
  # a brand-new SQLite store is created once, before the lanes write to it at once
  "$PYTHON" -c "import mlflow; mlflow.MlflowClient('$MLFLOW_TRACKING_URI').search_experiments()" >/dev/null 2>&1
  local pids=()
  for n in $(seq 1 "$lanes"); do lane "$n" & pids+=("$!"); done
  wait "${pids[@]}"
  rm -f "$QUEUE" "$QUEUE.lock"
}
