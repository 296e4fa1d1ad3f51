#!/usr/bin/env bash
# Structure by construction on a GPU machine (docs/results.md, "Constraints"): the shipped
# models fine-tuned through the constraint projection (`train --constraints on`, straight-
# through) against the same fine-tune without it, at equal time; the sparse P2G/G2P checked
# against the CPU backend; then the ablation on unseen scenes (simulate --seed 7, both
# families, every scene kind): none / each part / all, at inference only and trained
# through. CI has no GPU and does not run this. From the repository root, with
# `minflow-cuda` built with `--features cuda` in gpu/:
#
#   tests/gpu/constraints.sh data               # seed 1 (training) and seed 7 (unseen)
#   tests/gpu/constraints.sh transfer           # bench transfer: sparse against CPU and dense
#   tests/gpu/constraints.sh start MINUTES      # the fine-tunes below, in the background
#   tests/gpu/constraints.sh wait               # until they have ended
#   tests/gpu/constraints.sh ablation NAME...   # unseen scenes, every projection setting of
#                                               # each model: OUT/ablation-h20, OUT/ablation-full
#   tests/gpu/constraints.sh each NAME...       # each model in its own eval process, at once:
#                                               # off and on, horizon 20 (5 starts) and full
#                                               # (OUT/NAME-h20, OUT/NAME-full)
#   tests/gpu/constraints.sh pack               # the tables of OUT as OUT/tables.tgz
#
# Environment: OUT (logs and results, default /tmp/minflow-gpu), DATA (default /tmp/data).
set -uo pipefail
. "$(dirname "$0")/common.sh"
SMALL=(--grid 32 --unet-width 16 --levels 3 --reference none --bundle 4 --rollout-steps 4)
REST=(--model mingru --init-from models/all-grid-mingru-rest --rest-shape fit --rollout-steps 8)
SETTINGS=(--constraints off --constraints rope --constraints jelly --constraints liquid
    --constraints rope,jelly,liquid --constraints on)

case "${1:-}" in
data)
    make_data
    ;;
transfer)
    "$BIN" bench transfer --device cuda 2>&1 | tail -n 30
    # The network call with the dense and the sparse transfers, one model, the same scenes.
    for form in dense sparse; do
        MINFLOW_CUDA_TRANSFERS=$form "$BIN" bench rollout --device cuda --model models/all-grid-mingru \
            --constraints off --scenes 16 --batch 16 --threads 16 --frames 100 2>&1 | tail -n 2
    done
    ;;
start)
    m=$2
    # Through the projection, and its control at equal time.
    start rt "$m" "${REST[@]}" --constraints on
    start rc "$m" "${REST[@]}"
    start s4t "$m" --model mingru --init-from models/all-grid-mingru-small-k4 "${SMALL[@]}" \
        --constraints on
    ;;
wait)
    wait_runs
    ;;
ablation)
    shift
    model_flags "$@"
    "$BIN" eval "${models[@]}" "${SETTINGS[@]}" --device cuda --data "$DATA"/unseen --split all \
        --starts 5 --horizon 20 --no-render --out "$OUT/ablation-h20" >"$OUT/ablation-h20.log" 2>&1
    echo "horizon 20: exit $?"
    "$BIN" eval "${models[@]}" --constraints off --constraints on --device cuda \
        --data "$DATA"/unseen --split all --horizon full --out "$OUT/ablation-full" \
        >"$OUT/ablation-full.log" 2>&1
    echo "horizon full: exit $?"
    ;;
each)
    shift
    for name in "$@"; do
        model=$name
        [ -d "runs/$name" ] && model=runs/$name
        tag=$(basename "$name")
        for h in 20 full; do
            starts=(--starts 5 --no-render)
            [ "$h" = full ] && starts=()
            "$BIN" eval --model "$model" --constraints off --constraints on --device cuda \
                --data "$DATA"/unseen --split all --horizon "$h" "${starts[@]}" \
                --out "$OUT/$tag-h$h" >"$OUT/$tag-h$h.log" 2>&1 &
        done
    done
    wait
    ;;
pack)
    (cd "$OUT" && tar czf tables.tgz --exclude='*.gif' --exclude='*.png' */table.md */table.csv \
        */plausibility.csv */metrics.csv *.log 2>/dev/null; ls -la tables.tgz)
    ;;
*)
    sed -n '2,22p' "$0"
    exit 2
    ;;
esac
