#!/usr/bin/env bash
# Training at scale on a GPU machine (docs/training.md; CI has no GPU and does not run this).
# From the repository root, with gpu/minflow-cuda built with `--features cuda`:
#
#   tests/gpu/training.sh data      # 400 fluid scenes of 200 frames by the GPU solver (seed 11)
#   tests/gpu/training.sh stream    # the same run resident and streamed, side by side on two
#                                   # GPUs: samples/s of each epoch (metrics.csv)
#   tests/gpu/training.sh resume    # a run in three calls against the straight run on the GPU
#   tests/gpu/training.sh parallel  # bench train --arch grid on 1, 2 and 4 GPUs (GPUS=2, 8),
#                                   # the full shape on grids 32 and 64 and the small one
#                                   # (SHAPES), global batches 64 to 1024 (BATCHES)
#   tests/gpu/training.sh equal     # two GPUs against one: the same losses
#   tests/gpu/training.sh feed      # the batch feed alone (bench train --feed), both shapes,
#                                   # batch 1024, on 2, 8 and all cores: the rate no step
#                                   # on any GPU count can beat
#
# Parts run in the order given; logs and tables go to $OUT (default /tmp/minflow-gpu).
set -uo pipefail
# OUT, DATA, BIN (unpacked where needed), CUDA_PATH and NCCL.
. "$(dirname "$0")/common.sh"
SMALL=(--grid 32 --unet-width 16 --levels 3 --latent 32 --hidden 32 --head-hidden 64)

data() {
    /usr/bin/time -f "simulate: %e s, %M KiB" "$BIN" simulate --device cuda --family fluid \
        --seed 11 --scenes 0..400 --frames 200 --out "$DATA/fluid400" 2>&1 | tail -n 3
    du -sh "$DATA/fluid400"
}

# One 2-minute call of the demo model's shape on GPU $1 with --max-resident-frames $2.
stream_run() {
    "$BIN" train --device "cuda:$1" --data "$DATA/fluid400" --out "runs/stream-$2" "${SMALL[@]}" \
        --bundle 4 --rollout-steps 3 --batch-size 16 --samples-per-epoch 2000 --epochs 1000 \
        --val-starts 1 --val-horizon 20 --max-resident-frames "$2" --call-minutes 2 \
        >"$OUT/stream-$2.log" 2>&1
}

stream() {
    stream_run 0 auto &
    stream_run 1 20000 &
    wait
    for budget in auto 20000; do
        grep -E "streaming|scenes:" "$OUT/stream-$budget.log" | head -n 3
        echo "--max-resident-frames $budget: samples/s per epoch (first left out)"
        tail -n +3 "runs/stream-$budget/metrics.csv" | cut -d, -f5 | tr '\n' ' '
        echo
        awk -F, 'NR > 2 { s += $5; n++ } END { if (n) printf "mean %.1f over %d epochs\n", s / n, n }' \
            "runs/stream-$budget/metrics.csv"
    done
}

resume() {
    local tiny=(--data bags --grid 16 --levels 2 --unet-width 4 --latent 4 --hidden 4
        --head-hidden 8 --rollout-steps 2 --batch-size 4 --val-starts 1 --val-horizon 3
        --noise 0.1 --epochs 2 --model mingru --mirror --samples-per-epoch 16 --device cuda)
    rm -rf runs/straight runs/calls
    "$BIN" train "${tiny[@]}" --out runs/straight >/dev/null 2>&1
    "$BIN" train "${tiny[@]}" --out runs/calls --call-steps 3 >/dev/null 2>&1
    "$BIN" train "${tiny[@]}" --out runs/calls --call-steps 3 --resume >/dev/null 2>&1
    "$BIN" train "${tiny[@]}" --out runs/calls --call-steps 3 --resume >/dev/null 2>&1
    echo "straight:"; cat runs/straight/metrics.csv
    echo "three calls:"; cat runs/calls/metrics.csv
    python3 -c "import json; l = json.load(open('runs/calls/run.json')); \
print('ledger:', l['samples'], 'samples,', len(l['calls']), 'calls,', l['device_hours'], 'device-hours')"
}

# samples/s of bench train --arch grid on 1, 2, 4 (8) GPUs at global batches 64, 256 and 1024.
parallel() {
    local gpus=${GPUS:-4} list="cuda:0" shape batch net grid
    for n in $(seq 1 "$gpus"); do
        [ "$n" -gt 1 ] && list="$list,cuda:$((n - 1))"
        case $n in 1 | 2 | 4 | 8) ;; *) continue ;; esac
        # SHAPES: full-32, full-64 (the default network on grids of 32 and 64), small-32 (the
        # demo's network, `bench train --shape small`).
        for shape in ${SHAPES:-full-32 full-64 small-32}; do
            net=${shape%-*} grid=${shape#*-}
            for batch in ${BATCHES:-64 256 1024}; do
                echo "== $n GPU(s), $net shape, grid $grid, global batch $batch"
                "$BIN" bench train --arch grid --device "$list" --cores mingru --shape "$net" \
                    --grid "$grid" --micro-batch "$batch" --samples $((batch * 12)) --epochs 3 \
                    --warmup-epochs 1 --rollout-steps 4 2>&1 |
                    grep -E "^mingru|grid architecture|rror|panic"
            done
        done
    done
}

# The batch feed alone for 1, 2 and 4 shares, both shapes, on 2 and 8 of this machine's
# cores and on all of them (rayon's RAYON_NUM_THREADS; FEED_THREADS="2 8 all"): on a 2 x
# H200 machine's 32 cores it ran 2-3x slower than on a 2-core one, bound by the host's memory
# (docs/training.md).
feed() {
    local shape threads pool
    echo "$(nproc) cores; cgroup CPU quota: $(cat /sys/fs/cgroup/cpu.max 2>/dev/null || echo none)"
    for threads in ${FEED_THREADS:-2 8 all}; do
        pool=$threads
        [ "$threads" = all ] && pool=
        for shape in small full; do
            echo "== $shape shape, grid 32, batch 1024, $threads threads"
            # bash's own `time`: a bare machine may have no /usr/bin/time.
            TIMEFORMAT="%R s wall, %U s user, %S s sys"
            time (RAYON_NUM_THREADS=$pool "$BIN" bench train --arch grid --shape "$shape" \
                --grid 32 --micro-batch 1024 --samples 8192 --rollout-steps 4 --feed 2>&1 |
                tail -n 3)
        done
    done
}

# Two GPUs against one: the tiny network without input noise, 3 epochs; the losses agree
# to float noise.
equal() {
    local tiny=(--data bags --grid 16 --levels 2 --unet-width 4 --latent 4 --hidden 4
        --head-hidden 8 --rollout-steps 2 --batch-size 8 --val-starts 1 --val-horizon 3
        --noise 0 --epochs 3 --model mingru --samples-per-epoch 32)
    rm -rf runs/one runs/two
    "$BIN" train "${tiny[@]}" --device cuda:0 --out runs/one >"$OUT/one.log" 2>&1
    "$BIN" train "${tiny[@]}" --device cuda:0,cuda:1 --out runs/two >"$OUT/two.log" 2>&1 ||
        tail -n 5 "$OUT/two.log"
    echo "one GPU:"; cut -d, -f1-4 runs/one/metrics.csv
    echo "two GPUs:"; cut -d, -f1-4 runs/two/metrics.csv
}

for part in "$@"; do
    echo "### $part"
    "$part"
done
