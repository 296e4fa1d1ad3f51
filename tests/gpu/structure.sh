#!/usr/bin/env bash
# Structure on a GPU machine (docs/results_networks.md, "Structure"): the ablation at equal training
# time of the rest-shape features (fitted F), the grid velocity update (grid, grid+head
# against the free head) and the strain and volume losses, every run fine-tuned from a
# shipped model and all trained at once on one GPU; then the evaluation on unseen scenes
# (simulate --seed 7, both families, every scene kind) at horizon 20 and over whole scenes,
# with renders and structure metrics. CI has no GPU and does not run this. From the
# repository root, with `minflow-cuda` built with `--features cuda` in gpu/:
#
#   tests/gpu/structure.sh data              # seed 1 (training: 60 multi + 40 fluid scenes)
#                                            # and seed 7 (unseen: 10 multi + 6 fluid scenes)
#   tests/gpu/structure.sh start MINUTES     # every run below, in the background (setsid)
#   tests/gpu/structure.sh start3 MINUTES    # the third round: advected F against fitted F
#   tests/gpu/structure.sh start4 MINUTES    # the fourth: longer training rollouts
#   tests/gpu/structure.sh start5 MINUTES    # the fifth: push-forward
#   tests/gpu/structure.sh start7 MINUTES    # the seventh: chunks (truncated BPTT), memory
#   tests/gpu/structure.sh start8 MINUTES    # the eighth: the seventh's runs trained on
#   tests/gpu/structure.sh wait              # until they have ended, a line a minute
#   tests/gpu/structure.sh eval NAME...      # unseen scenes: horizon 20 (--starts 5) and full
#   tests/gpu/structure.sh eval-each NAME... # the same, one eval process per model, at once
#                                            # (OUT/NAME/unseen-h20, OUT/NAME/unseen-full)
#   tests/gpu/structure.sh pack DEST NAME... # run folders, tables and logs (renders of the
#                                            # NAMEs only) as DEST/results.tgz.part-*, 15 MB
#                                            # pieces (what a size-capped copy takes back)
#
# Environment: OUT (logs and results, default /tmp/minflow-gpu), DATA (default /tmp/data).
set -uo pipefail
. "$(dirname "$0")/common.sh"
SMALL=(--grid 32 --unet-width 16 --levels 3 --reference none --bundle 4 --rollout-steps 4)

# The structure losses' weights: at the shipped models' start each adds about 5 % to the
# rollout loss (measured on bags/ with the small model: strain 0.04, volume 0.33 per unit
# weight, beside an MSE term of about 2,100).
STRAIN=(--strain-loss 3000)
VOLUME=(--volume-loss 300)

case "${1:-}" in
data)
    make_data
    ;;
start)
    m=$2
    full=(--model mingru --init-from models/all-grid-mingru --rollout-steps 8)
    # Control: the same fine-tune without features or structure losses.
    start c0 "$m" "${full[@]}"
    # Rest-shape features alone, with the strain loss, with strain and volume losses.
    start f1 "$m" "${full[@]}" --rest-shape fit
    start fs "$m" "${full[@]}" --rest-shape fit "${STRAIN[@]}"
    start fsv "$m" "${full[@]}" --rest-shape fit "${STRAIN[@]}" "${VOLUME[@]}"
    # The losses without the features.
    start sv "$m" "${full[@]}" "${STRAIN[@]}" "${VOLUME[@]}"
    # Ten times the loss weights.
    start fsv10 "$m" "${full[@]}" --rest-shape fit --strain-loss 30000 --volume-loss 3000
    # The structured update: grid + the head's correction, and the grid field alone.
    start gh "$m" "${full[@]}" --rest-shape fit "${STRAIN[@]}" "${VOLUME[@]}" --update grid+head
    start g "$m" "${full[@]}" --rest-shape fit "${STRAIN[@]}" "${VOLUME[@]}" --update grid
    # The small bundled model with features and losses, and its control.
    start s4 "$m" --model mingru --init-from models/all-grid-mingru-small-k4 "${SMALL[@]}" \
        --rest-shape fit "${STRAIN[@]}" "${VOLUME[@]}"
    start s4c "$m" --model mingru --init-from models/all-grid-mingru-small-k4 "${SMALL[@]}"
    ;;
start2)
    # The second round, from the first round's features-only run (runs/f1, carried back):
    # it longer, a tenth of the strain weight alone, a tenth of the volume weight alone, and
    # the small bundled model with the features alone.
    m=$2
    f1=(--model mingru --init-from runs/f1 --rollout-steps 8 --rest-shape fit)
    start f1b "$m" "${f1[@]}"
    start fs3 "$m" "${f1[@]}" --strain-loss 300
    start fv30 "$m" "${f1[@]}" --volume-loss 30
    start s4f "$m" --model mingru --init-from models/all-grid-mingru-small-k4 "${SMALL[@]}" \
        --rest-shape fit
    ;;
start3)
    # The third round: F advected with the predicted velocities (variant (a)) against F
    # fitted to the rest neighbours (variant (b)), at equal time, from the same parents.
    m=$2
    full=(--model mingru --init-from models/all-grid-mingru --rollout-steps 8)
    start a1 "$m" "${full[@]}" --rest-shape advect
    start b1 "$m" "${full[@]}" --rest-shape fit
    # The advected liquid J with the volume loss (the lever the liquid's volume lacked).
    start av "$m" "${full[@]}" --rest-shape advect --volume-loss 30
    # The shipped fitted-F model switched to the advected F.
    start ra "$m" --model mingru --init-from models/all-grid-mingru-rest --rollout-steps 8 \
        --rest-shape advect
    # The small bundled model, each variant.
    start s4a "$m" --model mingru --init-from models/all-grid-mingru-small-k4 "${SMALL[@]}" \
        --rest-shape advect
    start s4b "$m" --model mingru --init-from models/all-grid-mingru-small-k4 "${SMALL[@]}" \
        --rest-shape fit
    ;;
start4)
    # The fourth round: longer rollouts in training (P calls, the loss over all of them),
    # from the shipped fitted-F model, at equal time; r8 is the same continuation at today's P.
    m=$2
    rest=(--model mingru --init-from models/all-grid-mingru-rest --rest-shape fit)
    start r8 "$m" "${rest[@]}" --rollout-steps 8
    start r16 "$m" "${rest[@]}" --rollout-steps 16
    start r32 "$m" "${rest[@]}" --rollout-steps 32
    start r32t "$m" "${rest[@]}" --rollout-steps 32 --teacher-steps 8
    ;;
start5)
    # The fifth round: push-forward (calls on the model's own predictions before the loss's,
    # no gradient), from the shipped fitted-F models, at equal time; p0 and s4c the controls.
    m=$2
    rest=(--model mingru --init-from models/all-grid-mingru-rest --rest-shape fit --rollout-steps 8)
    start p0 "$m" "${rest[@]}"
    start p24 "$m" "${rest[@]}" --pushforward 24
    start p56 "$m" "${rest[@]}" --pushforward 56
    start p120 "$m" "${rest[@]}" --pushforward 120
    small=(--model mingru --init-from models/all-grid-mingru-small-k4-rest "${SMALL[@]}" --rest-shape fit)
    start s4c "$m" "${small[@]}"
    start s4p "$m" "${small[@]}" --pushforward 14
    ;;
start7)
    # The seventh round: truncated backpropagation through time (the 8 loss calls made C times
    # per sample, an optimizer step after each, the rollout carried across: 64 and 128
    # frames) against today's one chunk, from the shipped fitted-F model; and the memory
    # ablation, minGRU against no memory, the small network from scratch (a fresh run's rate).
    m=$2
    rest=(--model mingru --init-from models/all-grid-mingru-rest --rest-shape fit --rollout-steps 8)
    start p0 "$m" "${rest[@]}"
    start c8 "$m" "${rest[@]}" --chunks 8
    start c16 "$m" "${rest[@]}" --chunks 16
    COMMON=("${COMMON[@]/#1e-4/1e-3}")
    scratch=(--grid 32 --unet-width 16 --levels 3 --rest-shape fit --rollout-steps 4)
    start sm0 "$m" --model mingru "${scratch[@]}"
    start smn "$m" --model none "${scratch[@]}"
    ;;
start8)
    # The eighth round: round 7's p0, c8 and c16 (their run folders carried back to the GPU
    # machine as gpu/r7/NAME) each trained MINUTES more on ordinary samples, so the chunks
    # are a first stage, at equal total time.
    m=$2
    for name in p0 c8 c16; do
        start "${name}p" "$m" --model mingru --init-from "gpu/r7/$name" --rest-shape fit \
            --rollout-steps 8
    done
    ;;
wait)
    wait_runs
    ;;
eval)
    shift
    eval_models "$@"
    ;;
eval-each)
    shift
    for name in "$@"; do
        model=runs/$name
        [ -d "$model" ] || model=$name
        dir="$OUT/$(basename "$name")"
        mkdir -p "$dir"
        (
            "$BIN" eval --model "$model" --device cuda --data "$DATA"/unseen --split all \
                --starts 5 --horizon 20 --no-render --out "$dir/unseen-h20" >"$dir/h20.log" 2>&1
            "$BIN" eval --model "$model" --device cuda --data "$DATA"/unseen --split all \
                --horizon full --out "$dir/unseen-full" >"$dir/full.log" 2>&1
            echo "$name: exit $?"
        ) &
    done
    wait
    ;;
pack)
    dest=$2
    shift 2
    list=$(mktemp)
    find runs -maxdepth 2 \( -name model.json -o -name model.mpk -o -name metrics.csv \
        -o -name split.json -o -name train.json -o -name loss.png \) >"$list"
    find "$OUT" \( -name '*.md' -o -name '*.csv' -o -name '*.log' \) >>"$list"
    for name in "$@"; do find "$OUT/$name" -name '*.png' >>"$list"; done
    tar -czf /tmp/results.tgz -T "$list"
    mkdir -p "$dest"
    split -b 15m /tmp/results.tgz "$dest/results.tgz.part-"
    ls -la "$dest"
    ;;
*)
    sed -n 2,24p "$0"
    exit 2
    ;;
esac
