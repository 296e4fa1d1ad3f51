#!/usr/bin/env bash
# The long run (issues 81 and 82: at least 10 million samples on at least 2,000 scenes,
# accumulated over device calls and sessions; docs/training.md, "The long run"). One call:
#
#   tests/gpu/long.sh call MINUTES
#
# 1. makes the dataset again (deterministic for its seeds, apart from the evaluation seeds 1
#    and 7): 1,000 `fluid` scenes (seed 11) and 1,000 `multi` scenes (seed 12) of 200 frames,
#    and the 16 unseen scenes of seed 7;
# 2. unpacks the run from gpu/long-run.tgz where there is one and trains it for MINUTES with
#    `--call-minutes` (a fresh run the first time, `--resume` after): the same schedule
#    whatever the calls, 50 epochs of 200,000 samples;
# 3. appends a point of the learning curve to runs/long/curve.csv (samples seen,
#    device-hours, avg20 of the model and of `constvel` on the unseen scenes from 5 starts);
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
    local sim=("$BIN" simulate --device "$DEVICE" --frames "$FRAMES")
    "${sim[@]}" --family fluid --seed 11 --scenes "0..$SCENES" --out "$DATA/long/fluid" | tail -n 1
    "${sim[@]}" --family multi --seed 12 --scenes "0..$SCENES" --out "$DATA/long/multi" | tail -n 1
    "$BIN" simulate --device "$DEVICE" --family multi --seed 7 --scenes 0..10 \
        --out "$DATA/long/unseen" | tail -n 1
    "$BIN" simulate --device "$DEVICE" --family fluid --seed 7 --scenes 0..6 \
        --out "$DATA/long/unseen" | tail -n 1
    du -sh "$DATA/long"/*
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

curve() {
    "$BIN" eval --model runs/long --device "$DEVICE" --data "$DATA/long/unseen" --split all \
        --starts 5 --horizon 20 --no-render --no-plausibility --out "$RET/unseen-h20" \
        >"$RET/unseen-h20.log" 2>&1 || { tail -n 5 "$RET/unseen-h20.log"; return 1; }
    python3 - "$RET/unseen-h20/table.csv" runs/long <<'PY'
import csv, json, os, sys
table, run = sys.argv[1], sys.argv[2]
row = next(r for r in csv.DictReader(open(table)) if r["scene"] == "Average")
ledger = json.load(open(os.path.join(run, "run.json")))
path = os.path.join(run, "curve.csv")
new = not os.path.exists(path)
with open(path, "a") as f:
    if new:
        f.write("samples,device_hours,avg20,avg20_constvel\n")
    f.write(f"{ledger['samples']},{ledger['device_hours']:.4f},{row['avg20_long']},"
            f"{row['avg20_constvel']}\n")
print(open(path).read())
PY
}

case "${1:-}" in
call)
    [ -n "${2:-}" ] || { echo "usage: $0 call MINUTES" >&2; exit 2; }
    data
    train "$2"
    curve
    tar czf "$RET/long-run.tgz" -C runs long
    ls -la "$RET/long-run.tgz"
    ;;
*)
    sed -n '2,20p' "$0"
    exit 2
    ;;
esac
