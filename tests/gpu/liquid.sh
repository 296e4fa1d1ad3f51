#!/usr/bin/env bash
# The liquid's levers at equal budget on one GPU (issue 81, docs/splash.md): small grid models trained from fresh weights side by side on the paper's 40
# `fluid` scenes (seed 1), each with one lever, then scored where the issue asks first, on
# the splash scenes they trained on, and on unseen `fluid` scenes (seed 7): avg20, whole
# scenes, liquid area and the surge front (tests/gpu/liquid_table.py). CI has no GPU and does
# not run this. From the repository root, with gpu/minflow-cuda built with `--features cuda`:
#
#   tests/gpu/liquid.sh data            # seed 1 fluid (training), seed 7 fluid 0..12 (unseen)
#   tests/gpu/liquid.sh train MINUTES   # the runs of LEVERS in the background, then waits
#   tests/gpu/liquid.sh eval NAME...    # runs/NAME (or paths): OUT/{train,unseen}-{h20,full}
#   tests/gpu/liquid.sh table NAME...   # the diagnosis table of those evaluations (and, for
#                                       # runs NAME-sN, each lever over its seeds)
#   tests/gpu/liquid.sh pack            # runs and evaluations as RET/{runs,liquid}.tgz
#
# LEVERS: space-separated NAME=FLAGS (flags joined by commas), default a plain run against the
# fast-particle loss at two weights. SEEDS (e.g. "1 2 3"): each lever once a seed, as
# NAME-sN on one split; at minutes of training the seeds differ as much as the levers do
# (docs/splash.md). BUNDLE (default 4): K of every run (1 for `--substeps`, e.g. BUNDLE=1
# LEVERS="plain= sub2=--substeps,2"). Environment as common.sh (OUT, DATA, BIN); RET
# (default OUT) for pack.
set -uo pipefail
. "$(dirname "$0")/common.sh"
RET=${RET:-$OUT}
SMALL=(--grid 32 --unet-width 16 --levels 3 --latent 32 --hidden 32 --head-hidden 64
    --bundle "${BUNDLE:-4}" --rollout-steps 4)
FRESH=(--epochs 1000 --patience 0 --lr 1e-3 --lr-final 1e-5 --noise 0.5 --mirror
    --batch-size 16 --samples-per-epoch 2000 --val-horizon 20 --val-starts 2)
LEVERS=${LEVERS:-"plain= fast1=--fast-loss,1 fast4=--fast-loss,4"}

case "${1:-}" in
data)
    "$BIN" simulate --device cuda --family fluid --seed 1 --out "$DATA/fluid" 2>&1 | tail -n 1
    "$BIN" simulate --device cuda --family fluid --seed 7 --scenes 0..12 \
        --out "$DATA/unseen_fluid" 2>&1 | tail -n 1
    ;;
train)
    # With SEEDS, each lever once a seed (LEVER-sN), all on the first seed's split: the runs
    # of the first seed start first, the others once its split.json is written.
    read -r -a seeds <<<"${SEEDS:-}"
    first=
    for seed in "${seeds[@]:-}"; do
        for lever in $LEVERS; do
            name=${lever%%=*}
            IFS=',' read -r -a flags <<<"${lever#*=}"
            if [ -n "$seed" ]; then
                name=$name-s$seed
                flags+=(--seed "$seed")
                if [ -z "$first" ]; then
                    first=runs/$name/split.json
                elif [ "$seed" != "${seeds[0]}" ]; then
                    for _ in $(seq 150); do [ -f "$first" ] && break; sleep 2; done
                    [ -f "$first" ] || { echo "no $first: the first run failed" >&2; exit 1; }
                    flags+=(--split-from "$first")
                fi
            fi
            setsid nohup "$BIN" train --device cuda --data "$DATA/fluid" --out "runs/$name" \
                --max-minutes "$2" "${SMALL[@]}" "${FRESH[@]}" "${flags[@]}" \
                >"$OUT/train-$name.log" 2>&1 &
            echo $! >>"$OUT/started.pids"
        done
    done
    wait_runs
    ;;
eval)
    shift
    model_flags "$@"
    # The scenes they fit, from the first run's split.json: its training scenes at horizon
    # 20 and their splash scenes whole.
    rm -rf "$DATA/train_all" "$DATA/train_splash"
    mkdir -p "$DATA/train_all" "$DATA/train_splash"
    for scene in $(python3 -c "import json, sys; print(' '.join(s.replace('/', '_') for s in \
        json.load(open(sys.argv[1]))['train']))" "${models[1]}/split.json"); do
        ln -sf "$DATA/fluid/$scene.mcap" "$DATA/train_all/"
        [[ $scene == *splash* ]] && ln -sf "$DATA/fluid/$scene.mcap" "$DATA/train_splash/"
    done
    for set in train:train_all:train_splash unseen:unseen_fluid:unseen_fluid; do
        IFS=':' read -r tag dir whole <<<"$set"
        "$BIN" eval "${models[@]}" --device cuda --data "$DATA/$dir" --split all \
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
pack)
    # The device tool brings back a few files a call: the runs (without checkpoints) and the
    # evaluations as two archives in RET.
    tar czf "$RET/runs.tgz" --exclude='checkpoint*' runs
    find "$OUT" -name '*.png' -delete
    tar czf "$RET/liquid.tgz" --exclude=runs.tgz --exclude=liquid.tgz \
        -C "$(dirname "$OUT")" "$(basename "$OUT")"
    ls -la "$RET"
    ;;
*)
    sed -n '2,20p' "$0"
    exit 2
    ;;
esac
