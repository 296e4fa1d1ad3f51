#!/usr/bin/env bash
# The grid architecture on a GPU machine (docs/grid.md): makes the paper-sized dataset with
# another seed than the bundled bags (so the bags stay held out), trains grid models there,
# and evaluates them on the test scenes. CI has no GPU and does not run this. From the
# repository root, with `minflow` built with `--features cuda` in gpu/ (plain or as
# gpu/minflow.xz, docs/cuda.md):
#
#   tests/gpu/grid.sh data                    # simulate: 60 multi + 40 fluid scenes, seed 1
#   tests/gpu/grid.sh extra A..B              # more multi scenes, ids A..B of seed 1, into
#                                             # $DATA/multi-extra (training only: train with
#                                             # --split-from, or --init-from a seed-1 run)
#   tests/gpu/grid.sh train NAME CORE MIN [FLAGS...]  # train runs/NAME (--max-minutes MIN)
#   tests/gpu/grid.sh start NAME CORE MIN [FLAGS...]  # the same in the background (setsid),
#                                             # on GPU $GPU: several runs, one per GPU
#   tests/gpu/grid.sh wait                    # until every started run has ended, a line a minute
#   tests/gpu/grid.sh eval NAME...            # eval --starts 5 at horizons 20 and 100
#   tests/gpu/grid.sh pack DEST NAME...       # run folders (no checkpoints), logs, tables -> DEST
#
# Environment: OUT (logs and results, default /tmp/minflow-gpu), DATA (default /tmp/data),
# GPU (the device ordinal of train/start/eval, default 0), EVAL_OUT (eval's folder name),
# EXTRA (non-empty: train also on $DATA/multi-extra).
set -uo pipefail
BIN=gpu/minflow
. "$(dirname "$0")/common.sh"

case "${1:-}" in
data)
    for family in multi fluid; do
        "$BIN" simulate --family "$family" --seed 1 --jobs "$(nproc)" --out "$DATA/$family" \
            2>&1 | tail -n 3 | tee -a "$OUT/data.log"
    done
    ;;
extra)
    "$BIN" simulate --family multi --seed 1 --scenes "$2" --jobs "$(nproc)" --out "$DATA/multi-extra" \
        2>&1 | tail -n 3 | tee -a "$OUT/data.log"
    ;;
train)
    name=$2 core=$3 minutes=$4
    shift 4
    "$BIN" train --device "cuda:${GPU:-0}" --data "$DATA"/multi "$DATA"/fluid ${EXTRA:+"$DATA"/multi-extra} --model "$core" --out "runs/$name" \
        --epochs 1000 --patience 0 --max-minutes "$minutes" "$@" >"$OUT/train-$name.log" 2>&1
    echo "train $name: exit $?"
    tail -n 4 "$OUT/train-$name.log"
    ;;
start)
    shift
    setsid nohup bash "$0" train "$@" >"$OUT/start-$1.log" 2>&1 &
    echo $! >>"$OUT/started.pids"
    echo "started $1 on GPU ${GPU:-0} (pid $!)"
    ;;
wait)
    wait_runs
    ;;
pack)
    dest=$2
    shift 2
    mkdir -p "$dest"
    for name in "$@"; do
        tar czf "$dest/run-$name.tgz" --exclude checkpoint --exclude checkpoint.old "runs/$name"
    done
    tar czf "$dest/logs.tgz" -C "$OUT" --exclude '*.mcap' .
    ;;
eval)
    shift
    models=()
    for name in "$@"; do models+=(--model "runs/$name"); done
    for horizon in 20 100; do
        dir="$OUT/${EVAL_OUT:-eval}-h$horizon"
        timeout "${EVAL_TIMEOUT:-300}" "$BIN" eval "${models[@]}" --device "cuda:${GPU:-0}" --data "$DATA"/multi "$DATA"/fluid \
            --starts 5 --horizon "$horizon" --no-render --out "$dir" >"$dir.log" 2>&1
        echo "eval horizon $horizon: exit $?"
        cat "$dir/table.md" 2>/dev/null || tail -n 20 "$dir.log"
    done
    ;;
*)
    sed -n 2,13p "$0"
    exit 2
    ;;
esac
