#!/usr/bin/env bash
# Temporal bundling on a GPU machine (issue 32; docs/results_networks.md, "Whole scenes"): the K = 1,
# 2, 4, 8 ablation at equal training time, the memory-against-none ablation at K = 4, and
# the small candidates, all trained at once on one GPU; then the evaluation on unseen
# scenes (simulate --seed 7, both families, every scene kind) at horizon 20 and over whole
# scenes, with renders. CI has no GPU and does not run this. From the repository root, with
# `minflow-cuda` built with `--features cuda` in gpu/ (plain or gpu/minflow-cuda.xz):
#
#   tests/gpu/bundle.sh data              # seed 1 (training: 60 multi + 40 fluid scenes)
#                                         # and seed 7 (unseen: 10 multi + 6 fluid scenes)
#   tests/gpu/bundle.sh start MINUTES     # every run below, in the background (setsid)
#   tests/gpu/bundle.sh wait              # until they have ended, a line a minute
#   tests/gpu/bundle.sh eval NAME...      # unseen scenes: horizon 20 (--starts 5) and full
#
# Environment: OUT (logs and results, default /tmp/minflow-gpu), DATA (default /tmp/data).
set -uo pipefail
. "$(dirname "$0")/common.sh"
SMALL=(--grid 32 --unet-width 16 --levels 3 --reference none)

case "${1:-}" in
data)
    make_data
    ;;
start)
    m=$2
    # K at equal time, each from the shipped single-frame minGRU (its head tiled K times),
    # P calls per sample so a sample covers 8-16 frames.
    start k1 "$m" --model mingru --init-from models/all-grid-mingru --bundle 1 --rollout-steps 8
    start k2 "$m" --model mingru --init-from models/all-grid-mingru --bundle 2 --rollout-steps 6
    start k4 "$m" --model mingru --init-from models/all-grid-mingru --bundle 4 --rollout-steps 4
    start k8 "$m" --model mingru --init-from models/all-grid-mingru --bundle 8 --rollout-steps 2
    # The small network (the CPU's budget) at K = 4 and 8, from the shipped small minGRU.
    start s4 "$m" --model mingru --init-from models/all-grid-mingru-small --bundle 4 \
        --rollout-steps 4 "${SMALL[@]}"
    start s8 "$m" --model mingru --init-from models/all-grid-mingru-small --bundle 8 \
        --rollout-steps 2 "${SMALL[@]}"
    # Memory against none at K = 4, both from fresh weights.
    start m4 "$m" --model mingru --bundle 4 --rollout-steps 4
    start n4 "$m" --model none --bundle 4 --rollout-steps 4
    ;;
wait)
    wait_runs
    ;;
eval)
    shift
    eval_models "$@"
    ;;
*)
    sed -n 2,15p "$0"
    exit 2
    ;;
esac
