# Shared by the GPU experiment scripts (bundle.sh, structure.sh): the binary, the training
# data, NCCL for data-parallel runs, one background training run, waiting for the runs, and
# a subset of them (ONLY). Sourced, not run. Sets OUT, DATA, BIN (unless the caller set it: gpu/minflow-cuda by
# default) and COMMON; the caller may add to COMMON after.
OUT=${OUT:-/tmp/minflow-gpu}
DATA=${DATA:-/tmp/data}
mkdir -p "$OUT" runs
export CUDA_PATH=${CUDA_PATH:-/usr/local/cuda}
BIN=${BIN:-gpu/minflow-cuda}
# NO_UNPACK=1: a caller that runs no binary (long.sh keep) leaves it packed.
if [ ! -x "$BIN" ] && [ -f "$BIN.xz" ] && [ -z "${NO_UNPACK:-}" ]; then
    python3 -c "import lzma, shutil; shutil.copyfileobj(lzma.open('$BIN.xz'), open('$BIN', 'wb'))"
    chmod +x "$BIN"
fi
# NCCL (data-parallel runs) where the system has none: PyTorch's wheel ships libnccl.so.2,
# which cudarc looks for as libnccl.so.
if ! ldconfig -p 2>/dev/null | grep -q "libnccl.so "; then
    nccl=$(python3 -c "import nvidia.nccl, os; print(os.path.join(list(nvidia.nccl.__path__)[0], 'lib'))" 2>/dev/null)
    if [ -n "$nccl" ] && [ -f "$nccl/libnccl.so.2" ]; then
        mkdir -p "$OUT/lib" && ln -sf "$nccl/libnccl.so.2" "$OUT/lib/libnccl.so"
        export LD_LIBRARY_PATH="$OUT/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    fi
fi
# SAMPLES (samples per epoch, default 2000), VAL_HORIZON (200) and VAL_STARTS (2) set the
# epoch's length and its validation rollouts.
COMMON=(--epochs 1000 --patience 0 --lr 1e-4 --lr-final 1e-6 --noise 0.5 --mirror
    --batch-size 16 --samples-per-epoch "${SAMPLES:-2000}" --val-horizon "${VAL_HORIZON:-200}"
    --val-starts "${VAL_STARTS:-2}")

# One training run in the background: NAME MINUTES FLAGS... With ONLY="a b" set, only the
# runs named there start (ten full-size runs at once do not fit in an H100's 80 GB). The
# training folders: TRAIN_DATA (space-separated), default the paper's two families.
start() {
    local name=$1 minutes=$2
    shift 2
    if [ -n "${ONLY:-}" ] && [[ " $ONLY " != *" $name "* ]]; then return; fi
    local data
    read -r -a data <<<"${TRAIN_DATA:-$DATA/multi $DATA/fluid}"
    setsid nohup "$BIN" train --device cuda --data "${data[@]}" --out "runs/$name" \
        --max-minutes "$minutes" "${COMMON[@]}" "$@" >"$OUT/train-$name.log" 2>&1 &
    echo $! >>"$OUT/started.pids"
}

# Seed 1 (training: 60 multi + 40 fluid scenes) and seed 7 (unseen: 10 multi + 6 fluid).
make_data() {
    for family in multi fluid; do
        "$BIN" simulate --family "$family" --seed 1 --jobs "$(nproc)" --out "$DATA/$family" \
            2>&1 | tail -n 2
    done
    "$BIN" simulate --family multi --seed 7 --scenes 0..10 --jobs "$(nproc)" --out "$DATA/unseen" \
        2>&1 | tail -n 2
    "$BIN" simulate --family fluid --seed 7 --scenes 0..6 --jobs "$(nproc)" --out "$DATA/unseen" \
        2>&1 | tail -n 2
}

# Until every started run has ended, a line per run each minute.
wait_runs() {
    while true; do
        running=0
        for pid in $(cat "$OUT/started.pids" 2>/dev/null); do
            kill -0 "$pid" 2>/dev/null && running=$((running + 1))
        done
        for log in "$OUT"/train-*.log; do
            [ -f "$log" ] || continue
            printf '%s: %s\n' "$(basename "$log" .log)" \
                "$(tail -c 300 "$log" | tr '\r' '\n' | grep -v '^$' | tail -n 1)"
        done
        [ "$running" -eq 0 ] && break
        sleep 60
    done
}

# The array `models`: `--model runs/NAME` for each NAME... that is a run here, `--model NAME`
# (a path) for the others.
model_flags() {
    models=()
    for name in "$@"; do
        if [ -d "runs/$name" ]; then models+=(--model "runs/$name"); else models+=(--model "$name"); fi
    done
}

# Every model NAME... (runs/NAME, or a path) on the unseen scenes at once: horizon 20 from 5
# starts (OUT/unseen-h20) and whole scenes with renders (OUT/unseen-full).
eval_models() {
    local models
    model_flags "$@"
    "$BIN" eval "${models[@]}" --device cuda --data "$DATA"/unseen --split all --starts 5 \
        --horizon 20 --no-render --out "$OUT/unseen-h20" >"$OUT/unseen-h20.log" 2>&1
    echo "horizon 20: exit $?"
    "$BIN" eval "${models[@]}" --device cuda --data "$DATA"/unseen --split all \
        --horizon full --out "$OUT/unseen-full" >"$OUT/unseen-full.log" 2>&1
    echo "horizon full: exit $?"
}
