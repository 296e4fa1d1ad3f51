#!/usr/bin/env bash
# The liquid's levers at equal budget on one GPU (issue 81, docs/liquid.md "Fitting the
# splash"): small grid models trained from fresh weights side by side on the paper's 40
# `fluid` scenes (seed 1), each with one lever, then scored where the issue asks first, on
# the splash scenes they trained on, and on unseen `fluid` scenes (seed 7): avg20, whole
# scenes, liquid area and the surge front (tests/gpu/liquid_table.py). CI has no GPU and does
# not run this. From the repository root, with gpu/minflow-cuda built with `--features cuda`:
#
#   tests/gpu/liquid.sh data            # seed 1 fluid (training), seed 7 fluid 0..12 (unseen)
#   tests/gpu/liquid.sh train MINUTES   # the runs of LEVERS in the background, then waits
#   tests/gpu/liquid.sh eval NAME...    # runs/NAME (or paths): OUT/{train,unseen}-{h20,full}
#   tests/gpu/liquid.sh table NAME...   # the diagnosis table of those evaluations
#
# LEVERS: space-separated NAME=FLAGS (flags joined by commas), default a plain run against the
# fast-particle loss at two weights. Environment as common.sh (OUT, DATA, BIN).
set -uo pipefail
. "$(dirname "$0")/common.sh"
SMALL=(--grid 32 --unet-width 16 --levels 3 --latent 32 --hidden 32 --head-hidden 64
    --bundle 4 --rollout-steps 4)
FRESH=(--epochs 1000 --patience 0 --lr 1e-3 --lr-final 1e-5 --noise 0.5 --mirror
    --batch-size 16 --samples-per-epoch 2000 --val-horizon 20 --val-starts 2)
LEVERS=${LEVERS:-"plain= fast1=--fast-loss,1 fast4=--fast-loss,4"}

case "${1:-}" in
data)
    "$BIN" simulate --device cuda --family fluid --seed 1 --out "$DATA/fluid" 2>&1 | tail -n 1
    "$BIN" simulate --device cuda --family fluid --seed 7 --scenes 0..12 \
        --out "$DATA/unseen" 2>&1 | tail -n 1
    ;;
train)
    for lever in $LEVERS; do
        name=${lever%%=*}
        IFS=',' read -r -a flags <<<"${lever#*=}"
        setsid nohup "$BIN" train --device cuda --data "$DATA/fluid" --out "runs/$name" \
            --max-minutes "$2" "${SMALL[@]}" "${FRESH[@]}" "${flags[@]}" \
            >"$OUT/train-$name.log" 2>&1 &
        echo $! >>"$OUT/started.pids"
    done
    wait_runs
    ;;
eval)
    shift
    models=()
    for name in "$@"; do
        if [ -d "runs/$name" ]; then models+=(--model "runs/$name"); else models+=(--model "$name"); fi
    done
    # The scenes they fit: the training split of the runs' seed-0 split over the same folder
    # at horizon 20, and its splash scenes (from the first run's split.json) whole.
    mkdir -p "$DATA/train_splash"
    for scene in $(python3 -c "import json, sys; print(' '.join(s.replace('/', '_') for s in \
        json.load(open(sys.argv[1]))['train'] if 'splash' in s))" "${models[1]}/split.json"); do
        ln -sf "$DATA/fluid/$scene.mcap" "$DATA/train_splash/"
    done
    for set in train:fluid:train:train_splash unseen:unseen:all:unseen; do
        IFS=':' read -r tag dir split whole <<<"$set"
        "$BIN" eval "${models[@]}" --device cuda --data "$DATA/$dir" --split "$split" \
            --starts 5 --horizon 20 --no-render --no-plausibility --out "$OUT/$tag-h20" \
            >"$OUT/$tag-h20.log" 2>&1 &
        "$BIN" eval "${models[@]}" --device cuda --data "$DATA/$whole" --split all \
            --horizon full --no-render --out "$OUT/$tag-full" >"$OUT/$tag-full.log" 2>&1 &
    done
    wait
    find "$OUT" -name 'front_*.png' -delete
    tail -n 2 "$OUT"/*-h20.log "$OUT"/*-full.log
    ;;
table)
    shift
    python3 "$(dirname "$0")/liquid_table.py" "$OUT" "$@"
    ;;
*)
    sed -n '2,16p' "$0"
    exit 2
    ;;
esac
