#!/usr/bin/env bash
# The long run (issues 81 and 82: at least 10 million samples on at least 2,000 scenes,
# accumulated over device calls and sessions; docs/training.md, "The long run"). One call:
#
#   tests/gpu/long.sh call MINUTES
#
# 1. makes the dataset (deterministic for its seeds, apart from the evaluation seeds 1 and
#    7; a warm machine keeps it from its last call): 1,000 `fluid` scenes (seed 11) and
#    1,000 `multi` scenes (seed 12) of 200 frames, and the 16 unseen scenes of seed 7;
# 2. unpacks the run from gpu/long-run.tgz where there is one and trains it for MINUTES with
#    `--call-minutes` (a fresh run the first time, `--resume` after): the same schedule
#    whatever the calls, 50 epochs of 200,000 samples;
# 3. appends a point of the learning curve to runs/long/curve.csv (samples seen,
#    device-hours; the latest weights' avg20 on the unseen scenes from 5 starts and their
#    whole scenes' MSE, beside `constvel`'s avg20 and `persist`'s whole scenes);
# 4. packs the run (model, checkpoint, ledger, curve) into $RET/long-run.tgz (RET defaults to
#    $OUT, the device tool's return folder). Copy it to gpu/long-run.tgz for the next call.
#
# Environment: BIN (gpu/minflow-cuda), DEVICE (cuda), DATA (/tmp/data), SCENES (1000 a
# family), FRAMES (200), NET (the model flags), SCHEDULE (the schedule flags). A CPU dry run:
# BIN=target/release/minflow DEVICE=cpu SCENES=4 FRAMES=12 NET="..." SCHEDULE="...".
set -uo pipefail
RET=${RET:-${OUT:-/tmp/minflow-gpu}}
# BIN (unpacked from BIN.xz where needed), DATA and CUDA_PATH.
. "$(dirname "$0")/common.sh"
DEVICE=${DEVICE:-cuda}
SCENES=${SCENES:-1000}
FRAMES=${FRAMES:-200}
read -r -a NET <<<"${NET:---grid 32 --unet-width 16 --levels 3 --latent 32 --hidden 32 \
    --head-hidden 64 --bundle 4 --rollout-steps 4 --model mingru}"
read -r -a SCHEDULE <<<"${SCHEDULE:---epochs 50 --samples-per-epoch 200000 --batch-size 128 \
    --lr 1e-3 --lr-final 1e-5 --patience 0 --noise 0.5 --mirror \
    --val-starts 1 --val-horizon 20}"
mkdir -p "$RET" runs

data() {
    # A warm machine keeps the last call's dataset: make it only once.
    if [ -f "$DATA/long/done-$SCENES-$FRAMES" ]; then
        echo "dataset kept from the last call: $DATA/long"
        return
    fi
    local sim=("$BIN" simulate --device "$DEVICE" --frames "$FRAMES")
    # The marker below is written only when every scene was made.
    "${sim[@]}" --family fluid --seed 11 --scenes "0..$SCENES" --out "$DATA/long/fluid" |
        tail -n 1 || return 1
    "${sim[@]}" --family multi --seed 12 --scenes "0..$SCENES" --out "$DATA/long/multi" |
        tail -n 1 || return 1
    "$BIN" simulate --device "$DEVICE" --family multi --seed 7 --scenes 0..10 \
        --out "$DATA/long/unseen" | tail -n 1 || return 1
    "$BIN" simulate --device "$DEVICE" --family fluid --seed 7 --scenes 0..6 \
        --out "$DATA/long/unseen" | tail -n 1 || return 1
    du -sh "$DATA/long"/*
    touch "$DATA/long/done-$SCENES-$FRAMES"
}

train() {
    local resume=()
    if [ -f gpu/long-run.tgz ] && [ ! -d runs/long ]; then
        tar xzf gpu/long-run.tgz -C runs
    fi
    [ -d runs/long/checkpoint ] && resume=(--resume)
    "$BIN" train --device "$DEVICE" --data "$DATA/long/fluid" "$DATA/long/multi" \
        --out runs/long "${NET[@]}" "${SCHEDULE[@]}" --call-minutes "$1" "${resume[@]}" \
        2>&1 | tr '\r' '\n' | grep -v "^\s*$" | tail -n 6
}

# The latest weights (the checkpoint's, with the run's model.json for the rest) as a model
# folder named `long`: the curve follows the training, not the best epoch so far.
latest() {
    rm -rf /tmp/latest && mkdir -p /tmp/latest/long
    cp runs/long/model.json /tmp/latest/long/ || return 1
    if [ -f runs/long/checkpoint/model.mpk ]; then
        cp runs/long/checkpoint/model.mpk /tmp/latest/long/
    else
        cp runs/long/model.mpk /tmp/latest/long/
    fi
}

curve() {
    latest || { echo "no model in runs/long yet: no curve point" >&2; return 1; }
    local eval=("$BIN" eval --model /tmp/latest/long --device "$DEVICE" --data "$DATA/long/unseen"
        --split all --no-render --no-plausibility)
    "${eval[@]}" --starts 5 --horizon 20 --out "$RET/unseen-h20" >"$RET/unseen-h20.log" 2>&1 ||
        { tail -n 5 "$RET/unseen-h20.log"; return 1; }
    "${eval[@]}" --horizon full --out "$RET/unseen-full" >"$RET/unseen-full.log" 2>&1 ||
        { tail -n 5 "$RET/unseen-full.log"; return 1; }
    python3 - "$RET" runs/long <<'PY'
import csv, json, os, sys
ret, run = sys.argv[1], sys.argv[2]
def average(name):
    return next(r for r in csv.DictReader(open(os.path.join(ret, name, "table.csv")))
                if r["scene"] == "Average")
h20, full = average("unseen-h20"), average("unseen-full")
ledger = json.load(open(os.path.join(run, "run.json")))
path = os.path.join(run, "curve.csv")
new = not os.path.exists(path)
with open(path, "a") as f:
    if new:
        f.write("samples,device_hours,avg20,avg20_constvel,whole,whole_persist\n")
    f.write(f"{ledger['samples']},{ledger['device_hours']:.4f},{h20['avg20_long']},"
            f"{h20['avg20_constvel']},{full['avg_full_long']},{full['avg_full_persist']}\n")
print(open(path).read())
PY
}

case "${1:-}" in
call)
    [ -n "${2:-}" ] || { echo "usage: $0 call MINUTES" >&2; exit 2; }
    start=$SECONDS
    data || { echo "the dataset could not be made" >&2; exit 1; }
    echo "dataset: $((SECONDS - start)) s"
    train "$2"
    echo "dataset and training: $((SECONDS - start)) s"
    curve
    echo "call: $((SECONDS - start)) s"
    tar czf "$RET/long-run.tgz" -C runs long
    ls -la "$RET/long-run.tgz"
    ;;
*)
    sed -n '2,21p' "$0"
    exit 2
    ;;
esac
