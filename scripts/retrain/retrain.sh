#!/usr/bin/env bash
# The whole retrain, from simulated data to the networks that ship:
#
#   data      generate the training set (2,000 episodes of the dynamic gait
#             and 400 of the hardware gait, joined), the long walking set
#             and a second, held-out test set of its own seed (sim/)
#   train     every network of the plan below, RETRAIN_PARALLEL at a time
#   calibrate Platt scaling or beta calibration (per horizon, by
#             cross-validation) of every network on the validation split
#   select    the network of each ablation to ship: EMP and MP by validation
#             loss, the fallbacks EP and P by their latch on validation
#   thresholds  the latch's trigger/release for each selected network (validation)
#   evaluate  eval on test (both protocols, seeds as mean +- std), warnings on
#             test and on the long walking set, by fall cause, at high sigma
#   card      the model card's tables from those reports; the results are kept
#             per run in models/card/ (commit it), so that seeds trained in
#             different data directories add up (scripts/retrain/model_card.py)
#   ship      copy the selected networks (f16) into models/, each network's
#             thresholds into config/ (scripts/retrain/ship_thresholds.py)
#
# `bash scripts/retrain/retrain.sh` runs every step in turn; `bash scripts/retrain/retrain.sh
# STEP` runs one. Stop it at any point and run it again: every step writes
# its outputs as .partial and renames them, a step whose output exists and
# is newer than its inputs is skipped, the generator resumes where it
# stopped and training resumes from its last epoch's checkpoint, so at most
# the step in progress (for training: its epoch) is lost. Progress goes to
# $FALL_GUARD_DATA/retrain.log with timestamps. In a new data directory the
# shipped networks are put back as the runs they are (and their kept
# thresholds and warnings with them), so that they are not trained again.
#
# Where:  FALL_GUARD_DATA (default ~/fall-guard-data): data sets, runs,
#         reports; keep it outside the work tree.
# Speed:  RETRAIN_JOBS generator processes (default: the core count);
#         RETRAIN_PARALLEL trainings side by side (default 2);
#         RETRAIN_DEVICE the training device (cpu, cuda, wgpu; a lab binary
#         built with that feature, FALL_GUARD_LAB_BIN, see docs/building.md).
# Cluster: RETRAIN_RAY=ADDRESS (a Ray head, HOST:PORT) runs the generation,
#         every training, calibration and evaluation as Ray tasks instead
#         (docs/retraining.md): the data directory on shared storage, the
#         same checkout path on every node. RETRAIN_TRAIN_CPUS CPUs per
#         training task (default 1), plus one GPU when RETRAIN_DEVICE is one.
# Smoke:  RETRAIN_TRAIN_ARGS="--epochs 1" adds arguments to every training.
# Scope:  RETRAIN_PAPER=1 also trains the `paper` configuration (last);
#         RETRAIN_RUNS="emp-s1 mp-s1 ..." trains only those runs of the plan
#         (the later steps use every run that exists), so that a machine
#         that cannot hold the whole plan in one sitting ships what it has.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPO=$(pwd)

DATA_ROOT=${FALL_GUARD_DATA:-$HOME/fall-guard-data}
# The lab names what lies here relative to it in its reports and model files,
# and every task on a cluster node finds the data directory at this same path.
export FALL_GUARD_DATA=$DATA_ROOT
JOBS=${RETRAIN_JOBS:-$(nproc)}
PARALLEL=${RETRAIN_PARALLEL:-2}
DEVICE=${RETRAIN_DEVICE:-cpu}
FG=${FALL_GUARD_LAB_BIN:-$REPO/target/release/fall-guard-lab}
PY=${SIM_PYTHON:-$REPO/sim/.venv/bin/python}
SET_NAME=simv6-mixed               # the training set's name: the two sets below, joined
# The training set, split by split (links to their episodes, compose_set.py);
# a task run elsewhere (`job`) gets the set its step was on, a subset by fall
# cause or the held-out set, as RETRAIN_SET.
SET=${RETRAIN_SET:-$DATA_ROOT/$SET_NAME}
DYNAMIC=$DATA_ROOT/simv6            # 2,000 episodes of the dynamic gait (generator 6, seed 1)
HARDWARE=$DATA_ROOT/simv6-hw        # 400 episodes of the hardware gait (the real walk's step, seed 21)
WALK=$DATA_ROOT/walk                # low sigma, no ball: false alarms per minute
HELDOUT=$DATA_ROOT/heldout          # a second test set, of its own seed (11) and plans
RUNS=$DATA_ROOT/runs
REPORTS=$DATA_ROOT/reports
LOG=$DATA_ROOT/retrain.log
mkdir -p "$DATA_ROOT" "$RUNS" "$REPORTS"
RAY=${RETRAIN_RAY:-}
TRAIN_CPUS=${RETRAIN_TRAIN_CPUS:-1}
case $DEVICE in cpu) TRAIN_GPUS=0 ;; *) TRAIN_GPUS=1 ;; esac

log() { printf '%s %s\n' "$(date -u +%Y-%m-%dT%H:%M:%SZ)" "$*" | tee -a "$LOG" >&2; }

# The variables a task run elsewhere needs from this shell (docs/retraining.md).
TASK_ENV=(FALL_GUARD_DATA FALL_GUARD_LAB_BIN SIM_PYTHON RETRAIN_DEVICE RETRAIN_TRAIN_ARGS RETRAIN_PAPER
          RETRAIN_RUNS RETRAIN_LATCH_MS RETRAIN_RELEASE_HOLD_MS)

# job FUNCTION ARGS...: run one unit of a step's work (a calibration, an
# evaluation, a warnings replay) now or, with RETRAIN_RAY, queue it as a
# Ray task of one CPU; `run_jobs` runs the queue. The task calls this script
# again (`task FUNCTION ARGS...`) with the SET this shell has now (RETRAIN_SET).
JOBS_QUEUE=$DATA_ROOT/.ray-jobs.$$
job() {
  if [ -z "$RAY" ]; then "$@"; return; fi
  printf '%s\n' "$(printf '%q ' env RETRAIN_SET="$SET" bash "$REPO/scripts/retrain/retrain.sh" task "$@")" >>"$JOBS_QUEUE"
}

# run_tasks CPUS GPUS: the commands on stdin (one a line) as Ray tasks of
# CPUS CPUs and GPUS GPUs each; fails when one of them failed.
run_tasks() {
  local envs=() v
  for v in "${TASK_ENV[@]}"; do envs+=(--env "$v"); done
  "$PY" "$REPO/scripts/retrain/ray_tasks.py" --address "$RAY" --cpus "$1" --gpus "$2" "${envs[@]}" | tee -a "$LOG" >&2
}

# run_jobs WHAT: the queued jobs (`job`), on Ray; nothing without RETRAIN_RAY.
run_jobs() {
  [ -n "$RAY" ] && [ -s "$JOBS_QUEUE" ] || return 0
  log "$1: $(wc -l <"$JOBS_QUEUE") tasks on Ray ($RAY)"
  local status=0
  run_tasks 1 0 <"$JOBS_QUEUE" || status=$?
  rm -f "$JOBS_QUEUE"
  return $status
}

# The data sets every warnings report is made from (the latch's thresholds
# are chosen on both, its figures taken on either).
DATA_SETS=("$SET/.complete" "$WALK/.complete")

# current OUT MODEL HORIZON_MS IN...: the warnings report OUT is newer than
# MODEL, both data sets and every IN, and is of MODEL at HORIZON_MS (a report
# of another run or horizon, from an earlier selection, or restored from
# models/card before the data sets were made, is made again).
current() {
  local out=$1 model=$2 horizon=$3; shift 3
  newer "$out" "$model" "${DATA_SETS[@]}" "$@" || return 1
  # The report names its model relative to the data directory (an
  # absolute path in a report written before that is taken too).
  "$PY" "$REPO/scripts/retrain/reports.py" current "$out" "$model" "$horizon" "$HOLD_MS" "$DATA_ROOT"
}

# newer OUT IN...: OUT exists and is newer than every IN.
newer() {
  local out=$1; shift
  [ -e "$out" ] || return 1
  local i
  for i in "$@"; do [ "$out" -nt "$i" ] || return 1; done
}

need_binary() {
  if [ ! -x "$FG" ]; then
    log "building $FG (cargo build --release -p fall-guard-lab)"
    cargo build --release --quiet -p fall-guard-lab
  fi
}

# The training plan: NAME and the `fall-guard-lab train` arguments. Order is
# priority (a cut drops from the end): EMP, MP and P seeds first, taken in
# turn, so that a run stopped early still has two seeds of each to compare.
plan() {
  local s
  for s in 1 2 3; do
    echo "emp-s$s --ablation EMP --seed $s"
    echo "mp-s$s --ablation MP --seed $s"
    echo "p-s$s --ablation P --seed $s"
  done
  # MP and P trained under the paper protocol (each horizon on its own
  # stop-line windows): the deployment windows hold almost no window that
  # ends 1-2 s before a fall, so there the 1.5 s and 2 s outputs learn what
  # the 1 s one does; these learn each horizon's own lead.
  for s in 1 2 3; do
    echo "mp-pp-s$s --ablation MP --seed $s --protocol paper"
    echo "p-pp-s$s --ablation P --seed $s --protocol paper"
  done
  for s in 1 2 3 4 5; do echo "emp-pp-s$s --ablation EMP --seed $s --protocol paper"; done
  echo "logreg-pp-s1 --ablation logreg --seed 1 --protocol paper"
  # The other ablations under the protocol the shipped networks train on, so
  # that they compare with the EMP seeds above.
  for s in 1 2 3; do echo "ep-pp-s$s --ablation EP --seed $s --protocol paper"; done
  for s in 1 2 3; do
    echo "emp-hist-pp-s$s --ablation EMP --seed $s --protocol paper --trajectory historical-only"
    echo "emp-real-pp-s$s --ablation EMP --seed $s --protocol paper --trajectory real-position"
  done
  for s in 1 2 3; do echo "emp-perh-s$s --ablation EMP --seed $s --protocol paper --per-horizon"; done
  # The vision encoder at the motion encoder's rate instead of the sim table's
  # 1e-6: whether the camera learns to see the ball coming once it can move.
  for s in 1 2 3; do echo "emp-vis-pp-s$s --ablation EMP --seed $s --protocol paper --vision-lr 1e-4"; done
  # The `paper` configuration (its cost per tick rules it out on the robot; its
  # accuracy is the question), under the protocol the shipped networks train on.
  if [ "${RETRAIN_PAPER:-0}" = 1 ]; then echo "emp-paper-pp-s1 --ablation EMP --seed 1 --config paper --protocol paper"; fi
}

# The runs `train` trains: the plan, or those of it RETRAIN_RUNS names.
train_plan() {
  local want=" ${RETRAIN_RUNS:-} " line
  while read -r line; do
    if [ -z "${RETRAIN_RUNS:-}" ]; then echo "$line"; continue; fi
    case $want in *" ${line%% *} "*) echo "$line" ;; esac
  done < <(plan)
}

KEEP=$REPO/models/card/$SET_NAME   # the results kept per run (scripts/retrain/model_card.py)
# The networks that ship are trained under the paper protocol (each horizon on
# its own stop-line windows, so that the 1.5 s and 2 s outputs learn their own
# lead), and the latch watches their LATCH_MS output (`[model].horizon_ms`),
# its thresholds chosen there on validation.
SHIP_PROTOCOL=-pp
LATCH_MS=${RETRAIN_LATCH_MS:-2000}
# The latch releases after this long below release (`[model].release_hold_ms`
# of the shipped configs; it delays a release, never an assertion).
HOLD_MS=${RETRAIN_RELEASE_HOLD_MS:-1000}
TRAINED_ON="$SET_NAME (sim generator 6: 2,000 dynamic-gait episodes, seed 1, and 400 hardware-gait episodes, seed 21; simulated data)"

# The shipped networks are calibrated runs of this plan: in a data directory
# without their run, put them back (RUNS/NAME.cal.bpk and NAME.done), with the
# thresholds and warnings kept for them, so that they are not trained again.
restore_shipped() {
  local abl f meta name
  for abl in emp mp ep p; do
    f=$REPO/models/$abl.bpk
    [ -e "$f" ] || continue
    meta=$("$PY" "$REPO/scripts/retrain/reports.py" shipped-run "$f" "$TRAINED_ON")
    set -- $meta
    [ "$1" = True ] && [ "$4" = planned ] || continue
    # The run's name in the plan: ABLATION[-pp]-sSEED (-pp: paper protocol).
    name=$2${5:-}-s$3
    [ -e "$RUNS/$name.cal.bpk" ] && continue
    log "restore: models/$abl.bpk is run $name (calibrated); not trained again"
    cp "$f" "$RUNS/$name.cal.bpk.partial"
    mv "$RUNS/$name.cal.bpk.partial" "$RUNS/$name.cal.bpk"
    touch "$RUNS/$name.done"
    if grep -qx "$abl $name .*" "$KEEP/reports/selected.txt" 2>/dev/null; then
      local r
      for r in "$KEEP/reports/$abl-thresholds.json" "$KEEP/reports/warnings-$abl-"*.json; do
        [ -e "$r" ] && [ ! -e "$REPORTS/$(basename "$r")" ] && cp "$r" "$REPORTS/"
      done
    fi
  done
  return 0
}

# Model file of a run (logreg is JSON; per-horizon runs write NAME.hH.bpk).
run_file() {
  case $1 in
    logreg-*) echo "$RUNS/$1.json" ;;
    *) echo "$RUNS/$1.bpk" ;;
  esac
}

# The generator's tasks on the cluster, with RETRAIN_RAY (`sim generate --ray`).
GENERATE_ON=()
[ -n "$RAY" ] && GENERATE_ON=(--ray "$RAY")

step_data() {
  log "data: $DYNAMIC (2,000 episodes of the dynamic gait, seed 1, $JOBS jobs)"
  "$PY" -m sim generate --out "$DYNAMIC" --episodes 2000 --seed 1 --jobs "$JOBS" "${GENERATE_ON[@]}" --quiet >>"$LOG"
  log "data: $HARDWARE (400 episodes of the hardware gait, seed 21)"
  "$PY" -m sim generate --out "$HARDWARE" --episodes 400 --seed 21 --gait hardware --jobs "$JOBS" \
    "${GENERATE_ON[@]}" --quiet >>"$LOG"
  log "data: $SET (the two joined split by split)"
  "$PY" "$REPO/scripts/retrain/compose_set.py" "$SET" --train "$DYNAMIC:train" --train "$HARDWARE:train" \
    --validation "$DYNAMIC:validation" --validation "$HARDWARE:validation" \
    --test "$DYNAMIC:test" --test "$HARDWARE:test" >>"$LOG"
  [ -e "$SET/.complete" ] || touch "$SET/.complete"   # once: a run is current while newer than it
  log "data: $WALK (300 walking episodes, sigma 0.005/0.01, no ball, seed 3)"
  "$PY" -m sim generate --out "$WALK" --episodes 300 --seed 3 --jobs "$JOBS" "${GENERATE_ON[@]}" --sigmas 0.005,0.01 \
    --ball-probability 0 --quiet >>"$LOG"
  [ -e "$WALK/.complete" ] || touch "$WALK/.complete"   # once: a run is current while newer than it
  log "data: $HELDOUT (600 episodes, seed 11: plans no other set walks)"
  "$PY" -m sim generate --out "$HELDOUT" --episodes 600 --seed 11 --jobs "$JOBS" "${GENERATE_ON[@]}" --quiet >>"$LOG"
  [ -e "$HELDOUT/.complete" ] || touch "$HELDOUT/.complete"   # once: a run is current while newer than it
  "$PY" -m sim stats "$SET" --counterfactual 150 --jobs "$JOBS" >"$REPORTS/set-stats.json.partial"
  mv "$REPORTS/set-stats.json.partial" "$REPORTS/set-stats.json"
  "$PY" -m sim stats "$WALK" >"$REPORTS/walk-stats.json.partial"
  mv "$REPORTS/walk-stats.json.partial" "$REPORTS/walk-stats.json"
  log "data: done"
}

# train_one NAME ARGS...: one run, resumable (checkpoint per epoch).
train_one() {
  local name=$1; shift
  local out
  out=$(run_file "$name")
  local done_marker="$RUNS/$name.done"
  if newer "$done_marker" "$SET/.complete"; then
    return 0
  fi
  local device=()
  case $name in logreg-*) ;; *) device=(--device "$DEVICE") ;; esac
  log "train $name: start ($*)"
  local t0=$SECONDS
  # --out .partial: the run writes there, checkpoints beside it; renamed when whole.
  local partial="${out%.*}.partial.${out##*.}"
  local extra=()
  read -r -a extra <<<"${RETRAIN_TRAIN_ARGS:-}"
  if /usr/bin/time -v -o "$RUNS/$name.time.txt" "$FG" train --data "$SET" "$@" "${extra[@]}" "${device[@]}" \
      --out "$partial" --trained-on "$TRAINED_ON" \
      --quiet >>"$RUNS/$name.log" 2>&1; then
    local f
    for f in "$RUNS/${name}".partial*; do
      [ -e "$f" ] || continue
      case $f in *.ckpt) continue ;; esac
      mv "$f" "${f/.partial/}"
    done
    touch "$done_marker"
    log "train $name: done in $((SECONDS - t0)) s"
  else
    log "train $name: FAILED after $((SECONDS - t0)) s (see $RUNS/$name.log)"
    return 1
  fi
}

step_train() {
  need_binary
  [ -e "$SET/.complete" ] || { log "train: the data set is not complete; run 'data' first"; return 1; }
  restore_shipped
  if [ -n "$RAY" ]; then
    log "train: $(train_plan | wc -l) runs on Ray ($RAY), $TRAIN_CPUS CPU and $TRAIN_GPUS GPU each"
    local line
    train_plan | while read -r line; do
      printf '%s\n' "$(printf '%q ' bash "$REPO/scripts/retrain/retrain.sh" task train_one) $line"
    done | run_tasks "$TRAIN_CPUS" "$TRAIN_GPUS"
  else
    log "train: $(train_plan | wc -l) runs, $PARALLEL at a time"
    export -f train_one run_file newer log
    export RUNS SET FG LOG DEVICE TRAINED_ON RETRAIN_TRAIN_ARGS
    train_plan | xargs -P "$PARALLEL" -L 1 bash -c 'train_one "$@"' _
  fi
  log "train: done"
}

# The validation loss of a run's network (its best epoch), for selection.
val_loss() { "$PY" "$REPO/scripts/retrain/model_meta.py" "$1" val_loss; }

# calibrated_by_form CAL: CAL's calibration names its forms per horizon (it
# was fitted by a `calibrate` that chooses between Platt scaling and beta
# calibration); one fitted before that is fitted again.
calibrated_by_form() {
  "$PY" "$REPO/scripts/retrain/model_meta.py" "$1" calibration | grep -q '; forms '
}

step_calibrate() {
  need_binary
  local name out cal src
  for name in $(plan | awk '{print $1}'); do
    case $name in
      logreg-*) continue ;;
      emp-perh-*) calibrate_per_horizon "$name"; continue ;;
    esac
    out=$(run_file "$name")
    cal="$RUNS/$name.cal.bpk"
    # A run restored from a shipped file has only its calibrated file, whose
    # weights are the network's (f16): it is calibrated again from those.
    src=$out
    [ -e "$src" ] || src=$cal
    [ -e "$src" ] || continue
    if [ -e "$cal" ] && { [ ! -e "$out" ] || newer "$cal" "$out"; } && calibrated_by_form "$cal"; then
      continue
    fi
    log "calibrate $name"
    local protocol=deployment
    case $name in *-pp-*) protocol=paper ;; esac
    job calibrate_file "$src" "$cal" "$protocol" "$RUNS/$name.log"
  done
  run_jobs calibrate
}

# calibrate_file SRC CAL PROTOCOL LOGFILE: SRC calibrated on the validation
# split under PROTOCOL, written to CAL (through CAL.partial).
calibrate_file() {
  "$FG" calibrate --model "$1" --data "$SET" --split validation --protocol "$3" \
    --out "$2.partial" --half >>"$4" 2>&1
  mv "$2.partial" "$2"
}

# calibrate_per_horizon NAME: each network of a per-horizon run (NAME.hH.bpk)
# calibrated as the all-horizon ones are, so that the two compare calibrated.
calibrate_per_horizon() {
  local f cal
  for f in "$RUNS/$1".h*.bpk; do
    case $f in *.cal.bpk) continue ;; esac
    [ -e "$f" ] || continue
    cal="${f%.bpk}.cal.bpk"
    newer "$cal" "$f" && continue
    log "calibrate $(basename "$f" .bpk)"
    job calibrate_file "$f" "$cal" paper "$RUNS/$1.log"
  done
}

# choose_on_validation MODEL HORIZON_MS OUT: MODEL's latch pair at HORIZON_MS
# chosen on the validation falls and walks (<= 0.1 false alarms per minute,
# `fall-guard-lab warnings --choose`), written to OUT.
choose_on_validation() {
  "$FG" warnings --model "$1" --data "$DATA_ROOT/choice" --split validation --choose \
    --horizon-ms "$2" --release-hold-ms "$HOLD_MS" --max-false-alarms-per-min 0.1 \
    --out "$3.partial" >>"$LOG" 2>&1
  mv "$3.partial" "$3"
}

# choose_pair RUN: RUN's latch pair at LATCH_MS chosen on validation
# (choose_on_validation), reports/choose-RUN.json; kept while current.
choose_pair() {
  local model="$RUNS/$1.cal.bpk" out="$REPORTS/choose-$1.json"
  current "$out" "$model" "$LATCH_MS" && return 0
  log "$1's pair at $LATCH_MS ms on validation falls and walks"
  choose_on_validation "$model" "$LATCH_MS" "$out"
}

# best_run GROUP [latch]: "RUN LOSS" of the calibrated seed of GROUP
# (GROUP-sN in the plan) with the lowest validation loss; nothing when none
# is calibrated. With `latch`, the seed whose latch, with its own pair
# chosen on validation (choose_pair), warns the most validation falls at
# least 0.5 s ahead, ties to the lower loss: the fallbacks (EP, P: what the
# daemon runs when the plan is lost) are chosen by what the daemon does
# with them (a lower loss has shipped a latch that, within the same alarm
# budget, warned half the falls).
best_run() {
  local best="" bestn=0 bestloss="" name loss n=0
  for name in $(plan | awk '{print $1}' | grep -E "^$1-s[0-9]+$"); do
    [ -e "$RUNS/$name.cal.bpk" ] || continue
    if [ "${2:-}" = latch ]; then
      choose_pair "$name"
      n=$("$PY" "$REPO/scripts/retrain/reports.py" warned-ahead "$REPORTS/choose-$name.json")
    fi
    loss=$(val_loss "$RUNS/$name.cal.bpk")
    if [ -z "$best" ] || [ "$n" -gt "$bestn" ] \
      || { [ "$n" -eq "$bestn" ] && awk -v a="$loss" -v b="$bestloss" 'BEGIN{exit !(a < b)}'; }; then
      best=$name; bestn=$n; bestloss=$loss
    fi
  done
  [ -n "$best" ] && echo "$best $bestloss"
  return 0
}

step_select() {
  local abl best
  need_binary
  restore_shipped
  "$PY" "$REPO/scripts/retrain/choice_set.py" "$SET" "$WALK" "$DATA_ROOT/choice" >>"$LOG"
  : >"$REPORTS/selected.txt.partial"
  for abl in emp mp ep p; do
    case $abl in
      ep | p) best=$(best_run "$abl$SHIP_PROTOCOL" latch) ;;
      *) best=$(best_run "$abl$SHIP_PROTOCOL") ;;
    esac
    [ -n "$best" ] && echo "$abl $best" >>"$REPORTS/selected.txt.partial"
  done
  mv "$REPORTS/selected.txt.partial" "$REPORTS/selected.txt"
  log "select: $(tr '\n' ';' <"$REPORTS/selected.txt")"
}

step_thresholds() {
  need_binary
  local abl name loss out
  # Validation falls with validation walking (the set's sigma <= 0.01 walks and
  # the walking set's validation split): false alarms are bounded per minute
  # of walking; the walking set's train and test splits give the test figure.
  "$PY" "$REPO/scripts/retrain/choice_set.py" "$SET" "$WALK" "$DATA_ROOT/choice" >>"$LOG"
  while read -r abl name loss; do
    out="$REPORTS/$abl-thresholds.json"
    current "$out" "$RUNS/$name.cal.bpk" "$LATCH_MS" && continue
    # The same choice `select` made for a fallback's seeds: made once.
    log "thresholds $abl ($name)"
    choose_pair "$name"
    cp "$REPORTS/choose-$name.json" "$out.partial"
    mv "$out.partial" "$out"
  done <"$REPORTS/selected.txt"
}

# seeds_of ABLATION-PREFIX: the calibrated runs of every seed.
seeds_of() {
  local name
  for name in $(plan | awk '{print $1}' | grep -E "^$1-s[0-9]+$"); do
    [ -e "$RUNS/$name.cal.bpk" ] && echo "$RUNS/$name.cal.bpk"
  done
  return 0
}

eval_group() { # eval_group LABEL PROTOCOL FILES...
  local label=$1 protocol=$2; shift 2
  local first=$1; shift
  local out="$REPORTS/eval-$label-$protocol"
  newer "$out/metrics.json" "$first" "$@" && return 0
  log "eval $label ($protocol, $((1 + $#)) seeds)"
  rm -rf "$out.partial"
  local seeds=()
  [ $# -gt 0 ] && seeds=(--seeds "$@")
  "$FG" eval --model "$first" "${seeds[@]}" --data "$SET" --split test --protocol "$protocol" \
    --draws 5 --out "$out.partial" >>"$LOG" 2>&1
  rm -rf "$out"; mv "$out.partial" "$out"
}

# eval_seeds GROUP LABEL: eval_group LABEL over the calibrated seeds of GROUP
# (nothing when it has none), on $SET.
eval_seeds() {
  local files
  mapfile -t files < <(seeds_of "$1")
  [ ${#files[@]} -gt 0 ] || return 0
  eval_group "$2" paper "${files[@]}"
}

# The evaluations, most needed first (a run stopped early has the comparison
# of EMP, MP and P and the daemon's warnings before the rest).
step_evaluate() {
  need_binary
  local group abl name loss
  # One eval reports both protocols (metrics.json `protocols`).
  for group in emp mp p emp-pp mp-pp p-pp; do job eval_seeds "$group" "$group"; done
  # Within the event episodes (the test episodes at sigma >= 0.035): whether
  # the plan and the camera add to the joints once an event is known to come.
  # The subsets by fall cause are made here too, with the test split's falls by
  # cause (reports/cause-stats.json, kept with the card's reports).
  "$PY" "$REPO/scripts/retrain/subset_by_cause.py" "$SET" "$DATA_ROOT/bycause" >>"$LOG"
  cp "$DATA_ROOT/bycause/causes.json" "$REPORTS/cause-stats.json.partial"
  mv "$REPORTS/cause-stats.json.partial" "$REPORTS/cause-stats.json"
  local causes cause
  causes=$("$PY" "$REPO/scripts/retrain/reports.py" causes "$DATA_ROOT/bycause")
  log "evaluate: test falls by cause: ${causes:-none}"
  for group in emp mp p emp-pp mp-pp p-pp; do
    SET="$DATA_ROOT/bycause/high-sigma" job eval_seeds "$group" "$group-highsigma"
  done
  # The daemon's own path: warnings on test and on the long walking set, then
  # on the test falls of each cause with the test walks.
  local target
  for target in set:test walk:train walk:test $(for cause in $causes; do echo "$cause:test"; done); do
    while read -r abl name loss; do
      job warnings_one "$abl" "$name" "$target"
    done <"$REPORTS/selected.txt"
  done
  # The real Poppy walk (tests/fixtures/real, no camera: the networks
  # without vision): time held on a walk no simulated episode holds, and the
  # out-of-range guard's share of its windows.
  mkdir -p "$DATA_ROOT/real"
  cp "$REPO/tests/fixtures/real/poppy_muffin_walk.mcap" "$DATA_ROOT/real/"
  printf '%s\n' '{"train": [], "validation": [], "test": ["poppy_muffin_walk.mcap"], "generator": {"name": "the real Poppy walk"}}' \
    >"$DATA_ROOT/real/manifest.json"
  while read -r abl name loss; do
    case $abl in mp | p) job warnings_one "$abl" "$name" real:test ;; esac
  done <"$REPORTS/selected.txt"
  # The latch on the 2 s output of the paper-trained networks (the lowest
  # validation loss of each): thresholds chosen at 2 s on the validation falls
  # and walks, then the test split and the walking set.
  local g best
  for g in emp-pp mp-pp p-pp; do
    best=$(best_run "$g")
    [ -n "$best" ] && job warnings_2s "${best%% *}"
  done
  # By fall cause: the networks on the test falls of one cause with the test walks.
  for cause in $causes; do
    for group in emp mp emp-pp mp-pp ep-pp p-pp emp-vis-pp; do
      SET="$DATA_ROOT/bycause/$cause" job eval_seeds "$group" "$group-$cause"
    done
  done
  # The camera's case on validation (the validation collision falls with the
  # validation walks), where the vision encoder's settings are compared.
  for group in emp-pp mp-pp emp-vis-pp; do
    SET="$DATA_ROOT/bycause/validation-collision" job eval_seeds "$group" "$group-valcollision"
  done
  for group in ep-pp emp-hist-pp emp-real-pp emp-paper-pp; do job eval_seeds "$group" "$group"; done
  # EMP trained per horizon (paper protocol): per horizon H, the calibrated
  # networks of every seed (emp-perh-sN.hH) on H's own windows.
  local h f files
  for h in $(find "$RUNS" -maxdepth 1 -name 'emp-perh-s*.h*.cal.bpk' \
      | sed -E 's/.*\.h([0-9]+)\.cal\.bpk$/\1/' | sort -nu); do
    files=()
    for f in "$RUNS"/emp-perh-s*.h"$h".cal.bpk; do files+=("$f"); done
    job eval_group "emp-perh.h$h" paper "${files[@]}"
  done
  if [ -e "$RUNS/logreg-pp-s1.json" ]; then
    job eval_group logreg paper "$RUNS/logreg-pp-s1.json"
  fi
  # The second test set (every episode of the held-out set): the test split's
  # 97 falls cannot tell an ECE of 0.03 from the noise; its ~300 can.
  if [ -e "$HELDOUT/.complete" ]; then
    "$PY" "$REPO/scripts/retrain/compose_set.py" "$DATA_ROOT/heldout-test" --test "$HELDOUT" >>"$LOG"
    for group in mp-pp p-pp emp-pp; do
      SET="$DATA_ROOT/heldout-test" job eval_seeds "$group" "$group-heldout"
    done
  fi
  # The networks that shipped before, on the same test split, for contrast:
  # the generator-1 ones (trained_on "simulated", the newest such version of
  # models/ABL.bpk in git's history) and the generator-4 ones (simv4).
  local rev blob tag on
  for abl in emp mp p; do
    for tag in gen1 gen4; do
      [ -e "$REPORTS/$tag-$abl.bpk" ] && continue
      for rev in $(git -C "$REPO" log --format=%H -- "models/$abl.bpk" 2>/dev/null); do
        blob="$REPORTS/$tag-$abl.bpk.partial"
        git -C "$REPO" show "$rev:models/$abl.bpk" >"$blob" 2>/dev/null || continue
        on=$("$PY" "$REPO/scripts/retrain/model_meta.py" "$blob" trained_on)
        if { [ $tag = gen1 ] && [ "$on" = simulated ]; } || { [ $tag = gen4 ] && [ "${on%% *}" = simv4 ]; }; then
          mv "$blob" "$REPORTS/$tag-$abl.bpk"
          break
        fi
        rm -f "$blob"
      done
    done
  done
  for abl in emp mp p; do
    for tag in gen1 gen4; do
      [ -e "$REPORTS/$tag-$abl.bpk" ] && job eval_group "$tag-$abl" paper "$REPORTS/$tag-$abl.bpk"
    done
  done
  run_jobs evaluate
}

# chosen_pair THRESHOLDS.json: "TRIGGER RELEASE", the chosen pair or, when none
# keeps within the budget, the grid's highest trigger.
chosen_pair() {
  "$PY" "$REPO/scripts/retrain/reports.py" chosen-pair "$1"
}

# latch_warnings MODEL THRESHOLDS.json HORIZON_MS SET:SPLIT OUT: the daemon's
# path (`fall-guard-lab warnings`) with the pair chosen in THRESHOLDS.json, on the
# data set (`set`), the walking set (`walk`; no choice is made on it) or the
# test falls of one cause with the test walks (any other name: the subset
# bycause/CAUSE); skipped while OUT is current (`current`; for a subset, newer
# than its manifest too, which subset_by_cause.py rewrites only when it changed).
latch_warnings() {
  local model=$1 pairs=$2 horizon=$3 target=$4 out=$5 trig rel
  local set=${target%%:*} split=${target##*:} data=$SET subset=()
  case $set in
    set) ;;
    walk) data=$WALK ;;
    real) data=$DATA_ROOT/real; subset=("$data/manifest.json") ;;
    *) data=$DATA_ROOT/bycause/$set; subset=("$data/manifest.json") ;;
  esac
  current "$out" "$model" "$horizon" "$pairs" "${subset[@]}" && return 0
  read -r trig rel < <(chosen_pair "$pairs")
  log "warnings $(basename "$model" .cal.bpk) at $horizon ms on $set $split (trigger $trig, release $rel)"
  "$FG" warnings --model "$model" --data "$data" --split "$split" --horizon-ms "$horizon" --trigger "$trig" \
    --release "$rel" --release-hold-ms "$HOLD_MS" --out "$out.partial" >>"$LOG" 2>&1
  mv "$out.partial" "$out"
}

# warnings_2s RUN: the latch on RUN's 2 s output, its pair chosen at 2 s on the
# validation falls and walks: reports/warn2s-RUN-{choose,set-test,walk-*}.json.
# For a shipped run whose latch is the 2 s one, these are its thresholds and
# warnings (steps thresholds and evaluate), copied.
warnings_2s() {
  local name=$1 model="$RUNS/$1.cal.bpk" out target abl f
  abl=$(awk -v n="$name" '$2 == n {print $1}' "$REPORTS/selected.txt")
  if [ "$LATCH_MS" = 2000 ] && [ -n "$abl" ]; then
    for target in choose set-test walk-train walk-test; do
      f="$REPORTS/warnings-$abl-$target.json"
      [ $target = choose ] && f="$REPORTS/$abl-thresholds.json"
      out="$REPORTS/warn2s-$name-$target.json"
      [ -e "$f" ] && ! newer "$out" "$f" && cp "$f" "$out"
    done
    return 0
  fi
  out="$REPORTS/warn2s-$name-choose.json"
  if ! newer "$out" "$model" "${DATA_SETS[@]}"; then
    log "warnings $name at 2 s: thresholds on validation falls and walks"
    choose_on_validation "$model" 2000 "$out"
  fi
  for target in set:test walk:train walk:test; do
    latch_warnings "$model" "$out" 2000 "$target" "$REPORTS/warn2s-$name-${target/:/-}.json"
  done
}

# warnings_one ABL RUN SET:SPLIT: the latch on RUN's LATCH_MS output with its
# ablation's thresholds (step_thresholds).
warnings_one() {
  latch_warnings "$RUNS/$2.cal.bpk" "$REPORTS/$1-thresholds.json" "$LATCH_MS" "$3" \
    "$REPORTS/warnings-$1-${3/:/-}.json"
}

step_card() {
  log "card: tables from $REPORTS and the results kept in $KEEP"
  "$PY" "$REPO/scripts/retrain/model_card.py" --reports "$REPORTS" --keep "$KEEP" \
    --out "$KEEP/tables.md.partial"
  mv "$KEEP/tables.md.partial" "$KEEP/tables.md"
}

step_ship() {
  local abl name loss
  while read -r abl name loss; do
    log "ship $abl: $name (validation loss $loss)"
    cp "$RUNS/$name.cal.bpk" "$REPO/models/$abl.bpk.partial"
    mv "$REPO/models/$abl.bpk.partial" "$REPO/models/$abl.bpk"
  done <"$REPORTS/selected.txt"
  # Each network's latch thresholds, chosen for it on validation, into the
  # configs (and the real walk's, which replays the shipped latch).
  "$PY" "$REPO/scripts/retrain/ship_thresholds.py" --reports "$REPORTS" --horizon-ms "$LATCH_MS" --release-hold-ms "$HOLD_MS" \
    "$REPO/config/replay.toml" "$REPO/config/poppy_humanoid.toml" "$REPO/tests/fixtures/real/replay.toml" \
    | tee -a "$LOG"
}

all_steps=(data train calibrate select thresholds evaluate card)
# `task FUNCTION ARGS...`: one unit of work handed to a Ray task (`job`,
# `step_train`), run where the task landed.
if [ "${1:-}" = task ]; then
  shift
  declare -F "${1:-}" >/dev/null || { echo "unknown task '${1:-}'" >&2; exit 2; }
  "$@"
  exit
fi
if [ $# -eq 0 ]; then
  for s in "${all_steps[@]}"; do "step_$s"; done
  log "retrain: every step done; 'bash scripts/retrain/retrain.sh ship' copies the networks into models/"
else
  for s in "$@"; do
    declare -F "step_$s" >/dev/null || { echo "unknown step '$s' (steps: ${all_steps[*]} ship)" >&2; exit 2; }
    "step_$s"
  done
fi
