#!/usr/bin/env bash
# The long run (issues 81 and 82: at least 10 million samples on at least 2,000 scenes,
# accumulated over device calls and sessions; docs/long_run.md). One call:
#
#   tests/gpu/long.sh call MINUTES
#
# 1. makes the dataset (deterministic for its seeds, apart from the evaluation seeds 1 and
#    7; a warm machine keeps it from its last call): 1,000 `fluid` scenes (seed 11) and
#    1,000 `multi` scenes (seed 12) of 200 frames (side by side on the first two GPUs of a
#    machine of several), and the 16 unseen scenes of seed 7;
# 2. trains the run for MINUTES with `--call-minutes` (`--resume` after its first call). It
#    has two phases, each a run folder with its own fixed schedule:
#    - phase 1, runs/long (gpu/long-run.tgz): fresh weights, 50 epochs of 200,000 samples at
#      batch 128; stopped at 1,622,208 samples (a step at batch 128 is partly bound by the
#      host's recording of its kernels; docs/long_run.md, "Why phase 2");
#    - phase 2, runs/long2 (gpu/long2-run.tgz): from phase 1's latest weights
#      (`--init-from`, its split and normalisation), 42 epochs of 200,000 samples at batch
#      512; its archive was lost at 4,029,120 samples (a new checkout does not keep gpu/);
#    - phase 3, runs/long3 (gpu/long3-run.tgz, else the committed models/long-run/; PHASE=3,
#      the default): from phase 2's epoch 8 as shipped (models/all-grid-mingru-small-k4-long,
#      3,223,744 samples), phase 2's other 34 epochs with its cosine begun again from where
#      epoch 8 left it (lr 9.1e-4), and the model's box wide (`--box-grid 256`,
#      docs/splash.md, "The model's box");
# 3. appends a point of the learning curve to the phase's curve.csv (not with CURVE=0, which
#    leaves the call's last 50 s to training; samples seen and
#    device-hours, the earlier phases' included; the latest weights' avg20 on the unseen
#    scenes from 5 starts and their whole scenes' MSE, beside `constvel`'s avg20 and
#    `persist`'s whole scenes; from phase 2 on also the liquid's area, energy and surge
#    fronts, liquid_table.py);
# 4. packs the phase's run folder (model, checkpoint, ledger, curve, the last 8 epochs'
#    weights in epochs/ for picking one by whole-scene eval or averaging them) into
#    $RET/$RUN-run.tgz (RET defaults to $OUT, the device tool's return folder). Copy it to
#    gpu/ for the next call, and at a session's end, without epochs/, to models/long-run/
#    (`tests/gpu/long.sh keep`): only what is committed outlives a checkout.
#
# Branches from a phase's latest weights (FROM: its run folder, phase 3's long3 by default,
# whose network flags they keep), for issue 81's levers at equal minutes from a trained
# model (each NAME=FLAGS, flags joined by commas, trains runs/branch-NAME side by side, on
# the machine's GPUs in turn, with the BRANCH schedule; then all are scored by
# tests/gpu/liquid_table.py on 12 splash scenes of the long run's training split and on
# the unseen scenes, and packed into $RET/branches.tgz):
#
#   tests/gpu/long.sh branch MINUTES plain= push4=--pushforward,4 mp2=--interaction,2
#
# (SCORE=0 trains only; `tests/gpu/long.sh score NAME=FLAGS...` then scores on the same
# warm machine, for branches whose training and scoring do not fit one call.)
#
# The kept epochs of the phase's run (`--keep-epochs 8`) scored on the unseen scenes, to
# pick the epoch to ship or to average by whole scenes: `tests/gpu/long.sh pick` (with
# the projection, as the demo runs them, on 2 CPU cores too:
# `PROJECTION=models/all-grid-mingru-small-k4-long BIN=target/release/minflow DEVICE=cpu
# tests/gpu/long.sh pick`, which unpacks models/long-run's archive, without epochs, where
# gpu/ holds none).
#
# Environment: BIN (gpu/minflow-cuda), DEVICE (cuda), TRAIN_DEVICE (the run's: every GPU
# of the machine, `cuda:0,cuda:1,...`, where it has several), DATA (/tmp/data), SCENES (1000 a
# family), FRAMES (200), PHASE (3), NET (the model flags), SCHEDULE (the phase's schedule
# flags), BRANCH (the branches' schedule). A CPU dry run: BIN=target/release/minflow
# DEVICE=cpu SCENES=4 FRAMES=24 SCHEDULE="..." BRANCH="..." (tiny epochs).
set -uo pipefail
RET=${RET:-${OUT:-/tmp/minflow-gpu}}
# BIN (unpacked from BIN.xz where needed: not for keep or the usage), DATA, CUDA_PATH and
# NCCL.
case "${1:-}" in keep | "") NO_UNPACK=1 ;; esac
. "$(dirname "$0")/common.sh"
DEVICE=${DEVICE:-cuda}
# The run trains on every GPU of the machine, data-parallel at the same global batch
# (docs/training.md, "Several GPUs"); TRAIN_DEVICE overrides. Datasets and evals use DEVICE.
GPUS=0
[ "$DEVICE" = cuda ] && GPUS=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU')
if [ -z "${TRAIN_DEVICE:-}" ]; then
    TRAIN_DEVICE=$DEVICE
    [ "${GPUS:-0}" -gt 1 ] && TRAIN_DEVICE=$(seq -s, -f 'cuda:%g' 0 $((GPUS - 1)))
fi
SCENES=${SCENES:-1000}
FRAMES=${FRAMES:-200}
read -r -a NET <<<"${NET:---grid 32 --unet-width 16 --levels 3 --latent 32 --hidden 32 \
    --head-hidden 64 --bundle 4 --rollout-steps 4 --model mingru}"
PHASE=${PHASE:-3}
# PHASE_NET: the phase's network flags beyond NET (its branches take them too).
PHASE_NET=()
case "$PHASE" in
1) RUN=long BATCH=(--epochs 50 --batch-size 128 --lr 1e-3) ;;
2) RUN=long2 BATCH=(--epochs 42 --batch-size 512 --lr 1e-3) ;;
# Phase 2's cosine from 1e-3 at its epoch 8 of 42: 1e-5 + 0.495e-3 (1 + cos(pi 8 / 42)).
3) RUN=long3 BATCH=(--epochs 34 --batch-size 512 --lr 9.1e-4) PHASE_NET=(--box-grid 256) ;;
*) echo "PHASE must be 1, 2 or 3" >&2; exit 2 ;;
esac
# Phase 3 starts from phase 2's epoch 8 as shipped; its ledger up to there, in earlier.json.
SHIPPED=models/all-grid-mingru-small-k4-long
read -r -a SCHEDULE <<<"${SCHEDULE:-${BATCH[*]} --samples-per-epoch 200000 \
    --lr-final 1e-5 --patience 0 --noise 0.5 --mirror --val-starts 1 --val-horizon 20 \
    --keep-epochs 8}"
read -r -a BRANCH <<<"${BRANCH:---epochs 1000 --samples-per-epoch 20000 --batch-size 128 \
    --lr 3e-4 --lr-final 3e-4 --patience 0 --noise 0.5 --mirror --val-starts 1 --val-horizon 20}"
mkdir -p "$RET" runs

data() {
    # A warm machine keeps the last call's dataset: make it only once.
    if [ -f "$DATA/long/done-$SCENES-$FRAMES" ]; then
        echo "dataset kept from the last call: $DATA/long"
        return
    fi
    local sim=("$BIN" simulate --frames "$FRAMES") fluid=$DEVICE multi=$DEVICE made
    # On a machine of several GPUs the two families are made side by side, one a GPU.
    [ "${GPUS:-0}" -gt 1 ] && fluid=cuda:0 multi=cuda:1
    # The marker below is written only when every scene was made.
    (
        "${sim[@]}" --device "$fluid" --family fluid --seed 11 --scenes "0..$SCENES" \
            --out "$DATA/long/fluid" | tail -n 1
    ) &
    made=$!
    if [ "$fluid" = "$multi" ]; then
        wait "$made" || return 1
        made=
    fi
    if ! "${sim[@]}" --device "$multi" --family multi --seed 12 --scenes "0..$SCENES" \
        --out "$DATA/long/multi" | tail -n 1; then
        # The other family stops too: a later call on this machine makes both again.
        [ -z "$made" ] || { pkill -P "$made"; kill "$made"; wait "$made"; } 2>/dev/null
        return 1
    fi
    [ -z "$made" ] || wait "$made" || return 1
    unseen || return 1
    du -sh "$DATA/long"/*
    touch "$DATA/long/done-$SCENES-$FRAMES"
}

# The 16 unseen scenes of seed 7 (the README's), alone: all `pick` needs.
unseen() {
    # A dataset made before this marker existed holds them too.
    if [ -f "$DATA/long/unseen/done" ] || compgen -G "$DATA/long/done-*" >/dev/null; then
        return
    fi
    "$BIN" simulate --device "$DEVICE" --family multi --seed 7 --scenes 0..10 \
        --out "$DATA/long/unseen" | tail -n 1 || return 1
    "$BIN" simulate --device "$DEVICE" --family fluid --seed 7 --scenes 0..6 \
        --out "$DATA/long/unseen" | tail -n 1 || return 1
    touch "$DATA/long/unseen/done"
}

# runs/$1 from gpu/$1-run.tgz (else the committed models/long-run/$1-run.tgz), where this
# machine does not hold it yet.
unpack() {
    local packed
    [ -d "runs/$1" ] && return
    for packed in "gpu/$1-run.tgz" "models/long-run/$1-run.tgz"; do
        [ -f "$packed" ] && { tar xzf "$packed" -C runs; return; }
    done
}

# The latest weights of the run $1 (long: phase 1, long2: phase 2; unpacked from
# gpu/$1-run.tgz where needed) as the model folder /tmp/from/$1, where phase 2 and the
# branches start.
from_run() {
    unpack "$1"
    latest "$1" /tmp/from ||
        { echo "no run $1 (gpu/$1-run.tgz) to start from" >&2; return 1; }
}

train() {
    local start=()
    unpack long
    unpack "$RUN"
    if [ -d "runs/$RUN/checkpoint" ]; then
        start=(--resume)
    elif [ "$RUN" = long2 ]; then
        from_run long || return 1
        start=(--init-from /tmp/from/long)
    elif [ "$RUN" = long3 ]; then
        start=(--init-from "$SHIPPED")
    fi
    echo "training on $TRAIN_DEVICE"
    "$BIN" train --device "$TRAIN_DEVICE" --data "$DATA/long/fluid" "$DATA/long/multi" \
        --out "runs/$RUN" "${NET[@]}" "${PHASE_NET[@]}" "${SCHEDULE[@]}" --call-minutes "$1" \
        "${start[@]}" \
        2>&1 | tr '\r' '\n' | grep -v "^\s*$" | tail -n 6
    # Phase 1's ledger goes with phase 2's folder (and archive): its curve counts both.
    if [ "$RUN" = long2 ] && [ ! -f runs/long2/phase1.json ]; then
        cp runs/long/run.json runs/long2/phase1.json
    fi
    # Phase 3's start: phase 1 (1,622,208 samples, 0.62 device-hours) and phase 2's first 8
    # epochs of 200,192 samples; phase 2's ledger was lost with its archive, so its hours
    # to epoch 8 are read off the two points around it (2,243,136 samples at 0.80 hours,
    # 3,608,384 at 1.40, docs/long_run.md).
    if [ "$RUN" = long3 ] && [ ! -f runs/long3/earlier.json ]; then
        echo '{"samples": 3223744, "device_hours": 1.23, "from": "'"$SHIPPED"'",' \
            '"note": "phase 1 and phase 2 to its epoch 8; hours interpolated"}' \
            >runs/long3/earlier.json
    fi
}

# The latest weights of runs/$1 (the checkpoint's, with the run's model.json for the rest)
# as a model folder $2/$1: the curve follows the training, not the best epoch so far.
latest() {
    local to=$2/$1
    rm -rf "$2" && mkdir -p "$to"
    cp "runs/$1/model.json" "$to/" || return 1
    # The split, so that `--init-from` keeps the run's held-out scenes.
    [ -f "runs/$1/split.json" ] && cp "runs/$1/split.json" "$to/"
    if [ -f "runs/$1/checkpoint/model.mpk" ]; then
        cp "runs/$1/checkpoint/model.mpk" "$to/"
    else
        cp "runs/$1/model.mpk" "$to/"
    fi
}

curve() {
    latest "$RUN" /tmp/latest || { echo "no model in runs/$RUN yet: no curve point" >&2; return 1; }
    local eval=("$BIN" eval --model "/tmp/latest/$RUN" --device "$DEVICE"
        --data "$DATA/long/unseen" --split all --no-render)
    "${eval[@]}" --starts 5 --horizon 20 --no-plausibility --out "$RET/unseen-h20" \
        >"$RET/unseen-h20.log" 2>&1 || { tail -n 5 "$RET/unseen-h20.log"; return 1; }
    # Whole scenes with the structure measures: the liquid's area, energy and surge front.
    "${eval[@]}" --horizon full --out "$RET/unseen-full" >"$RET/unseen-full.log" 2>&1 ||
        { tail -n 5 "$RET/unseen-full.log"; return 1; }
    # Later phases' points count the earlier phases' samples and device-hours too.
    python3 - "$RET" "$RUN" "$(dirname "$0")" <<'PY'
import csv, json, os, sys
ret, name = sys.argv[1], sys.argv[2]
sys.path.insert(0, sys.argv[3])
from liquid_table import areas, fronts
run = os.path.join("runs", name)
def average(table):
    return next(r for r in csv.DictReader(open(os.path.join(ret, table, "table.csv")))
                if r["scene"] == "Average")
h20, full = average("unseen-h20"), average("unseen-full")
ledgers = [json.load(open(os.path.join(run, f)))
           for f in ("run.json", "phase1.json", "earlier.json")
           if os.path.exists(os.path.join(run, f))]
samples = sum(l["samples"] for l in ledgers)
hours = sum(l["device_hours"] for l in ledgers)
path = os.path.join(run, "curve.csv")
columns = "samples,device_hours,avg20,avg20_constvel,whole,whole_persist"
# The liquid's measures over its 11 scenes (tests/gpu/liquid_table.py): area over the
# truth's at steps 20 / 200 / the end (scenes within 10 %), kinetic energy over the truth's,
# surge fronts within 10 % of the truth's step. A curve begun without them goes on without.
liquid = ",liquid_area_20_200_end,liquid_energy,fronts"
area, energy, _ = areas(os.path.join(ret, "unseen-full", "plausibility.csv"), name)
front = fronts(os.path.join(ret, "unseen-full", "front.csv"), name)
if not os.path.exists(path):
    open(path, "w").write(columns + liquid + "\n")
with_liquid = open(path).readline().strip().endswith(liquid)
with open(path, "a") as f:
    f.write(f"{samples},{hours:.4f},{h20['avg20_' + name]},{h20['avg20_constvel']},"
            f"{full['avg_full_' + name]},{full['avg_full_persist']}")
    f.write(f",{area},{energy},{front}\n" if with_liquid else "\n")
print(open(path).read())
PY
}

# Trains each NAME=FLAGS of "$@" (after MINUTES, $1) from FROM's latest weights, side by
# side, into runs/branch-NAME; on a machine of several GPUs they take the GPUs in turn.
branch() {
    local minutes=$1 from=${FROM:-$RUN} pids=() lever name flags device net=()
    shift
    # A branch of this phase keeps its network flags.
    [ "$from" = "$RUN" ] && net=("${PHASE_NET[@]}")
    from_run "$from" || return 1
    for lever in "$@"; do
        name=branch-${lever%%=*}
        IFS=',' read -r -a flags <<<"${lever#*=}"
        device=$DEVICE
        [ "${GPUS:-0}" -gt 1 ] && device=cuda:$((${#pids[@]} % GPUS))
        "$BIN" train --device "$device" --data "$DATA/long/fluid" "$DATA/long/multi" \
            --out "runs/$name" --init-from "/tmp/from/$from" "${NET[@]}" "${net[@]}" \
            "${BRANCH[@]}" --max-minutes "$minutes" "${flags[@]}" >"$RET/train-$name.log" 2>&1 &
        pids+=($!)
    done
    # The branches that trained, for `score`.
    TRAINED=()
    for i in "${!pids[@]}"; do
        lever=${*:$((i + 1)):1}
        if wait "${pids[$i]}"; then
            TRAINED+=("$lever")
        else
            echo "branch ${lever%%=*} failed: $RET/train-branch-${lever%%=*}.log" >&2
        fi
        tail -n 3 "$RET/train-branch-${lever%%=*}.log" | tr '\r' '\n' | grep -v "^\s*$" | tail -n 2
    done
}

# The branches of "$@" (NAME=FLAGS, as `branch`) scored as liquid.sh scores its levers, into
# $RET/branches/{train,unseen}-{h20,full}: `train` is 12 splash scenes of the long run's
# training split (the fit), `unseen` the 16 scenes of seed 7.
score() {
    local models=() names=() lever out=$RET/branches split
    for lever in "$@"; do
        names+=("branch-${lever%%=*}")
        models+=(--model "runs/branch-${lever%%=*}")
    done
    rm -rf "$DATA/long/train_splash" "$out" && mkdir -p "$DATA/long/train_splash" "$out"
    # The training split is phase 1's: every later phase, branch and the shipped model keep it.
    for split in $(python3 -c "import json, sys; print(' '.join(s.replace('/', '_') for s in \
        json.load(open(sys.argv[1]))['train'] if s.startswith('fluid/splash')))" \
        "$SHIPPED/split.json"); do
        [ -f "$DATA/long/fluid/$split.mcap" ] && ln -sf "$DATA/long/fluid/$split.mcap" \
            "$DATA/long/train_splash/"
        [ "$(ls "$DATA/long/train_splash" | wc -l)" -ge 12 ] && break
    done
    evaluate "$out" train:train_splash unseen:unseen
    for name in "${names[@]}"; do
        mkdir -p "$out/runs/$name"
        cp "runs/$name"/{metrics.csv,model.json,run.json} "$out/runs/$name/" 2>/dev/null
    done
    tar czf "$RET/branches.tgz" -C "$RET" branches
}

# Evaluates the models of the caller's `models` (named as its `names`) on each SET:FOLDER of
# "$@" (after OUT, $1; folders under $DATA/long) into OUT/SET-h20 and OUT/SET-full, and
# prints liquid_table.py's table into OUT/table.md.
evaluate() {
    local out=$1 set
    shift
    for set in "$@"; do
        local eval=("$BIN" eval "${models[@]}" --device "$DEVICE" --data "$DATA/long/${set#*:}"
            --split all --no-render)
        "${eval[@]}" --starts 5 --horizon 20 --no-plausibility --out "$out/${set%%:*}-h20" \
            >"$out/${set%%:*}-h20.log" 2>&1 || tail -n 5 "$out/${set%%:*}-h20.log"
        "${eval[@]}" --horizon full --out "$out/${set%%:*}-full" >"$out/${set%%:*}-full.log" \
            2>&1 || tail -n 5 "$out/${set%%:*}-full.log"
    done
    python3 "$(dirname "$0")/liquid_table.py" "$out" "${names[@]}" | tee "$out/table.md"
    find "$out" -name '*.png' -delete
}

# The epochs runs/$RUN kept (`train --keep-epochs`) scored on the unseen scenes as `score`
# scores branches, into $RET/pick and $RET/pick.tgz: the epoch to ship is picked by whole
# scenes, and the ones to average (`minflow average`), not by the 20-frame validation loss.
# PROJECTION=DIR scores them as the demo runs them: copies of the epochs with DIR's
# constraints (`constraints copy`), beside DIR itself; EPOCHS="0010 0011" scores only those.
pick() {
    local models=() names=() dir out=$RET/pick kept=0
    unpack "$RUN"
    if [ -n "${PROJECTION:-}" ]; then
        names+=("$(basename "$PROJECTION")")
        models+=(--model "$PROJECTION")
    fi
    for dir in runs/"$RUN"/epochs/*/; do
        [ -f "$dir/model.mpk" ] || continue
        # EPOCHS="0010 0011": only those kept epochs.
        [ -z "${EPOCHS:-}" ] || [[ " $EPOCHS " == *" $(basename "$dir") "* ]] || continue
        if [ -n "${PROJECTION:-}" ]; then
            rm -rf "/tmp/pick/$(basename "$dir")" && mkdir -p /tmp/pick &&
                cp -r "${dir%/}" /tmp/pick/ && dir=/tmp/pick/$(basename "$dir")/ &&
                "$BIN" constraints copy --from "$PROJECTION" --model "$dir" >/dev/null ||
                return 1
        fi
        names+=("$(basename "$dir")")
        models+=(--model "${dir%/}")
        kept=$((kept + 1))
    done
    [ "$kept" -gt 0 ] || {
        echo "no kept epochs in runs/$RUN/epochs${EPOCHS:+ among $EPOCHS} (runs/$RUN unpacked" \
            "from an archive without them? remove it to unpack gpu/$RUN-run.tgz)" >&2
        return 1
    }
    rm -rf "$out" && mkdir -p "$out"
    evaluate "$out" unseen:unseen
    tar czf "$RET/pick.tgz" -C "$RET" pick
}

case "${1:-}" in
keep)
    # Here, not on the device: the last call's archive, without its kept epochs, committed.
    mkdir -p models/long-run /tmp/keep && rm -rf "/tmp/keep/$RUN" &&
        tar xzf "gpu/$RUN-run.tgz" -C /tmp/keep &&
        tar czf "models/long-run/$RUN-run.tgz" -C /tmp/keep --exclude "$RUN/epochs" \
            --exclude "$RUN/checkpoint.old" "$RUN" &&
        ls -la "models/long-run/$RUN-run.tgz"
    ;;
branch)
    [ -n "${2:-}" ] && [ -n "${3:-}" ] ||
        { echo "usage: $0 branch MINUTES NAME=FLAGS..." >&2; exit 2; }
    start=$SECONDS
    data || { echo "the dataset could not be made" >&2; exit 1; }
    echo "dataset: $((SECONDS - start)) s"
    branch "${@:2}" || exit 1
    echo "training: $((SECONDS - start)) s"
    [ "${#TRAINED[@]}" -gt 0 ] || { echo "no branch trained" >&2; exit 1; }
    # SCORE=0 leaves the scoring to a `score` call on the same warm machine.
    [ "${SCORE:-1}" = 0 ] || score "${TRAINED[@]}"
    echo "call: $((SECONDS - start)) s"
    ;;
pick)
    start=$SECONDS
    unseen || { echo "the unseen scenes could not be made" >&2; exit 1; }
    pick || exit 1
    echo "call: $((SECONDS - start)) s"
    ;;
score)
    [ -n "${2:-}" ] || { echo "usage: $0 score NAME=FLAGS..." >&2; exit 2; }
    start=$SECONDS
    score "${@:2}"
    echo "call: $((SECONDS - start)) s"
    ;;
call)
    [ -n "${2:-}" ] || { echo "usage: $0 call MINUTES" >&2; exit 2; }
    start=$SECONDS
    data || { echo "the dataset could not be made" >&2; exit 1; }
    echo "dataset: $((SECONDS - start)) s"
    train "$2"
    echo "dataset and training: $((SECONDS - start)) s"
    # CURVE=0: no curve point this call (about 50 s more of training in a call's 10 minutes).
    [ "${CURVE:-1}" = 0 ] || curve
    echo "call: $((SECONDS - start)) s"
    tar czf "$RET/$RUN-run.tgz" -C runs "$RUN"
    ls -la "$RET/$RUN-run.tgz"
    ;;
*)
    sed -n '2,57p' "$0"
    exit 2
    ;;
esac
