#!/usr/bin/env bash
# GPU checks and benchmarks of docs/cuda.md, for a CUDA machine (CI has no GPU and does not
# run this). From the repository root, with `minflow` built with `--features cuda` in gpu/
# (plain, or xz-compressed as gpu/minflow.xz; docs/cuda.md says how):
#
#   tests/gpu/run.sh speed     # PyTorch reference, bench gemm, bench train per --gpu-gemm, five cores
#   tests/gpu/run.sh autotune  # the paper's model with burn's autotuned kernels (cuda-autotune)
#   tests/gpu/run.sh profile   # host timings per micro-batch and cubecl's kernel profile
#   tests/gpu/run.sh parity    # CPU and GPU train the same model from the same seed and data
#   tests/gpu/run.sh node      # the surrogate node on the GPU over zenoh and iceoryx2
#   tests/gpu/run.sh batched   # the shipped grid models' step on 1-256 scenes at once
#   tests/gpu/run.sh multi     # data parallel on two GPUs: parity with one GPU, throughput
#   tests/gpu/run.sh grid      # the grid model: the GPU's im2col kernels against the composed
#                              # ones (same first-epoch loss, samples/s), and PyTorch's step
#   tests/gpu/run.sh kernels   # cubecl's kernel profile of a grid training step (batch 16) and
#                              # of a 256-scene network call (docs/kernels.md, "Roofline")
#   tests/gpu/run.sh call256   # every shipped model's 256-scene call against the solver, the
#                              # node at 256 streams x 62.5 Hz, and eval on the GPU (its
#                              # metrics.csv to compare with a CPU run of the same command)
#   tests/gpu/run.sh fused     # the Adam kernel against burn's composed step (training, the
#                              # same first-epoch loss) and the implicit-GEMM convolutions
#                              # against im2col (the 256-scene call, eval's table within 1e-3)
#   tests/gpu/run.sh sparse    # the sparse transfers (bench transfer: CPU, dense, bits), and
#                              # training and the 256-scene call with sparse against dense
#                              # transfers, beside PyTorch's training step
#   tests/gpu/run.sh solver    # the MLS-MPM solver batched on the GPU: validation checks 2-5
#                              # and 7 (gpu/it.xz: the `it` tests built with --features cuda),
#                              # its cost and physics against the CPU's at 2,500, 10,000 and
#                              # 40,000 particles, and two `simulate --device cuda` runs' bags
#   tests/gpu/run.sh projection # the projection on the device against the host's
#                              # (gpu/it.xz), and the fluid family's 256-scene call with each
#   tests/gpu/run.sh cudnn     # the convolutions through cuDNN against im2col and cuBLAS:
#                              # training beside PyTorch's step (and cuDNN on weights copied
#                              # into its layout each pass, the form before), the 256-scene
#                              # call with its stages, eval's tables within 1e-3
#
# Logs go to $OUT (default /tmp/minflow-gpu). A part that fails prints FAIL and the script
# goes on with the next one; the exit code is the number of failed parts.
set -uo pipefail
OUT=${OUT:-/tmp/minflow-gpu}
mkdir -p "$OUT"
export CUDA_PATH=${CUDA_PATH:-/usr/local/cuda}
# NVLink multicast stays off (the machines' rule; NCCL is not used by the multi-device
# strategy, but keep it so for any library that loads NCCL).
export NCCL_NVLS_ENABLE=0
BIN=gpu/minflow
# PyTorch for the reference timings: python3, or the machine's torch venv.
PY=${PY:-python3}
if ! "$PY" -c "import torch" 2>/dev/null && [ -x /opt/torch/.venv/bin/python ]; then
    PY=/opt/torch/.venv/bin/python
fi
if [ ! -x "$BIN" ] && [ -f gpu/minflow.xz ]; then
    python3 -c "import lzma, shutil; shutil.copyfileobj(lzma.open('gpu/minflow.xz'), open('$BIN', 'wb'))"
    chmod +x "$BIN"
fi
# cuDNN (the default convolutions where it loads): the system's, or the wheel PyTorch brings.
if ! ldconfig -p 2>/dev/null | grep -q 'libcudnn.so.9'; then
    CUDNN_LIB=$("$PY" -c 'import nvidia.cudnn, os; print(os.path.join(list(nvidia.cudnn.__path__)[0], "lib"))' 2>/dev/null)
    [ -d "$CUDNN_LIB" ] && export LD_LIBRARY_PATH="$CUDNN_LIB${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
fi
failed=0
check() { # name command...
    local name=$1
    shift
    echo "=== $name: $*"
    if "$@" 2>&1 | tee -a "$OUT/$name.log"; then echo "--- $name ok"; else
        echo "--- $name FAIL"
        failed=$((failed + 1))
    fi
}

speed() {
    nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv
    # PyTorch on the same GPU, the paper's configuration (ELU encoder, batch 80, T = 2).
    check torch "$PY" tools/torch_reference.py --cores mingru,gru,minlstm,lstm,mlp --steps 20 --warmup 3
    # The encoder's products alone: cubecl vs cuBLAS TF32 / FP32.
    check gemm "$BIN" bench gemm --device cuda
    # The paper's model per product kernel (cubecl: with and without split-K), then the
    # five cores.
    for gemm in tf32 fp32 cubecl; do
        check "paper-gemm-$gemm" "$BIN" bench train --device cuda --encoder-last-activation elu \
            --windows 2 --cores mingru --micro-batch 80 --samples 800 --epochs 2 \
            --warmup-epochs 1 --gpu-gemm "$gemm"
    done
    check paper-split-off "$BIN" bench train --device cuda --encoder-last-activation elu \
        --windows 2 --cores mingru --micro-batch 80 --samples 800 --epochs 2 \
        --warmup-epochs 1 --gpu-gemm cubecl --split-weight-grad off
    check paper-cores "$BIN" bench train --device cuda --encoder-last-activation elu --windows 2 \
        --micro-batch 80 --samples 800 --epochs 2 --warmup-epochs 1
    # minflow's default encoder (pool-then-project), T = 2 and 32.
    check cheap-cores "$BIN" bench train --device cuda --windows 2,32 --micro-batch 80 \
        --samples 400 --epochs 2 --warmup-epochs 1
}

autotune() { # burn's autotuned kernels (gpu/minflow-at: --features cuda-autotune); the tuning
    # results land in target/autotune (reused by later runs from this folder)
    local at=gpu/minflow-at
    if [ ! -x "$at" ] && [ -f gpu/minflow-at.xz ]; then
        python3 -c "import lzma, shutil; shutil.copyfileobj(lzma.open('$at.xz'), open('$at', 'wb'))"
        chmod +x "$at"
    fi
    for core in mingru gru; do
        check "autotune-$core" "$at" bench train --device cuda --encoder-last-activation elu \
            --windows 2 --cores "$core" --micro-batch 80 --samples 800 --epochs 2 --warmup-epochs 1
    done
    tar czf "$OUT/autotune.tgz" target/autotune 2>/dev/null
}

profile() { # where a step's time goes: host timings per micro-batch, then cubecl's kernel profile
    local cheap=(bench train --device cuda --windows 32 --cores mingru --micro-batch 80
        --samples 160 --epochs 1 --warmup-epochs 1)
    local paper=(bench train --device cuda --encoder-last-activation elu --windows 2
        --cores mingru --micro-batch 80 --samples 320 --epochs 1 --warmup-epochs 1)
    RUST_LOG=minflow::train=trace check host-cheap32 "$BIN" "${cheap[@]}"
    RUST_LOG=minflow::train=trace check host-paper "$BIN" "${paper[@]}"
    CUBECL_DEBUG_OPTION=profile-full CUBECL_DEBUG_LOG="$OUT/kernels-cheap32.txt" \
        check prof-cheap32 "$BIN" "${cheap[@]}"
    CUBECL_DEBUG_OPTION=profile-full CUBECL_DEBUG_LOG="$OUT/kernels-paper.txt" \
        check prof-paper "$BIN" "${paper[@]}"
}

data() { # the dataset of the parity runs: 10 multi scenes of 60 frames (deterministic bags)
    [ -d "$OUT/data" ] || "$BIN" simulate --family multi --scenes 0..10 --frames 60 \
        --out "$OUT/data" >/dev/null 2>&1
    (cd "$OUT/data" && md5sum *.mcap | md5sum)
}

parity() {
    data
    local common=(--data "$OUT/data" --model mingru --width 256 --encoder-hidden 128
        --encoder-last-activation elu --batch-size 16 --micro-batch 16 --epochs 5 --seed 3
        --patience 0)
    check parity-gpu "$BIN" train "${common[@]}" --device cuda --out "$OUT/runs/gpu"
    check parity-cpu "$BIN" train "${common[@]}" --device cpu --out "$OUT/runs/cpu"
    paste -d, "$OUT/runs/cpu/metrics.csv" "$OUT/runs/gpu/metrics.csv" | tee "$OUT/parity.csv"
}

node() {
    [ -d "$OUT/runs/gpu" ] || parity
    for transport in zenoh iceoryx2; do
        check "node-$transport" "$BIN" launch replay_eval model:="$OUT/runs/gpu" device:=cuda \
            transport:="$transport" bags:=bags out:="$OUT/replay-$transport"
    done
}

batched() { # one step over many scenes, frames/s (docs/speed.md, "The node on one GPU")
    nvidia-smi --query-gpu=name,driver_version --format=csv
    check batched "$BIN" bench node --device cuda --skip-node --batch 1,4,16,64,256 \
        --model models/all-grid-mingru --model models/all-grid-minlstm \
        --model models/all-grid-mingru-small
}

multi() {
    nvidia-smi --query-gpu=index,name,memory.total --format=csv
    data
    # dropout 0: two GPUs then compute the one-GPU gradient (up to summation order).
    local common=(--data "$OUT/data" --model mingru --width 256 --encoder-hidden 128
        --encoder-last-activation elu --batch-size 16 --micro-batch 16 --epochs 5 --seed 3
        --patience 0 --dropout 0)
    check multi-one "$BIN" train "${common[@]}" --device cuda:0 --out "$OUT/runs/one"
    check multi-two "$BIN" train "${common[@]}" --device cuda:0,cuda:1 --out "$OUT/runs/two"
    paste -d, "$OUT/runs/one/metrics.csv" "$OUT/runs/two/metrics.csv" | tee "$OUT/multi.csv"
    for devices in cuda:0 cuda:0,cuda:1; do
        check "multi-bench-$devices" "$BIN" bench train --device "$devices" \
            --encoder-last-activation elu --windows 2 --cores mingru --micro-batch 160 \
            --samples 1600 --epochs 2 --warmup-epochs 1
    done
}

grid() { # docs/grid.md, "GPU speed"
    nvidia-smi --query-gpu=name,driver_version --format=csv
    for b in 16 32; do
        check "grid-conv-$b" "$BIN" bench train --arch grid --device cuda --cores mingru \
            --conv shift,gather --micro-batch "$b" --samples $((8 * b)) --epochs 3 \
            --warmup-epochs 1 --stages
        # Both kernels start from the same weights and data: the first epoch's loss (the last
        # column) must agree to float rounding, else the GPU's im2col / col2im is wrong (a NaN
        # loss is no number and fails too).
        check "grid-conv-$b-agree" awk '$1 == "mingru" && $NF ~ /^[0-9]/ { loss[$2] = $NF }
            END { ok = ("shift" in loss) && ("gather" in loss)
                  d = loss["shift"] - loss["gather"]; if (d < 0) d = -d
                  if (!ok || d > 1e-5 * loss["shift"]) {
                      print "first-epoch losses differ:", loss["shift"], loss["gather"]; exit 1 }
                  print "first-epoch losses agree:", loss["shift"], loss["gather"] }' \
            "$OUT/grid-conv-$b.log"
        check "grid-torch-$b" "$PY" tools/torch_grid_reference.py --memory mingru \
            --precision fp32,tf32 --batch "$b"
    done
}

kernels() { # docs/kernels.md, "Roofline": every kernel of a training step and of a network call
    CUBECL_DEBUG_OPTION=profile-full CUBECL_DEBUG_LOG="$OUT/kernels-train16.txt" \
        check prof-train16 "$BIN" bench train --arch grid --device cuda --cores mingru \
        --micro-batch 16 --samples 32 --epochs 1 --warmup-epochs 1
    CUBECL_DEBUG_OPTION=profile-full CUBECL_DEBUG_LOG="$OUT/kernels-call256.txt" \
        check prof-call256 "$BIN" bench rollout --device cuda --model models/all-grid-mingru \
        --constraints off --scenes 256 --batch 256 --threads 16 --frames 3
    gzip -f "$OUT"/kernels-*.txt
}

call256() { # docs/speed.md, "A predicted frame against a solver frame"; docs/scale.md
    local models=()
    for m in models/*/; do [ -f "$m/model.json" ] && models+=(--model "${m%/}"); done
    check rollout-256-all "$BIN" bench rollout --device cuda "${models[@]}" --constraints off \
        --scenes 256 --batch 256 --threads 16 --frames 20
    for m in all-grid-mingru all-grid-mingru-small-k4; do
        check "node-$m" "$BIN" bench node --device cuda --model "models/$m" --streams 256 \
            --rate 62.5 --max-batch 256 --warm-up 12 --seconds 12
    done
    check eval-gpu "$BIN" eval --device cuda --model models/all-grid-mingru \
        --model models/all-grid-mingru-small-k4 --data bags --split all --starts 3 --no-render \
        --constraints off --out "$OUT/eval-gpu"
}

grid_forms() { # VAR TAG FORM...: bench train --arch grid at batch 16 and 32 with VAR set to
    # each FORM (logs grid-TAG FORM-B), then PyTorch's step at that batch
    local var=$1 tag=$2
    shift 2
    for b in 16 32; do
        for form in "$@"; do
            check "grid-$tag$form-$b" env "$var=$form" "$BIN" bench train --arch grid \
                --device cuda --cores mingru --micro-batch "$b" --samples $((8 * b)) --epochs 3 \
                --warmup-epochs 1 --stages
        done
        check "grid-torch-$b" "$PY" tools/torch_grid_reference.py --memory mingru \
            --precision fp32,tf32 --batch "$b"
    done
}

sparse() { # docs/cuda.md, "Sparse transfers"
    nvidia-smi --query-gpu=name,driver_version --format=csv
    check transfer "$BIN" bench transfer --device cuda
    grid_forms MINFLOW_CUDA_TRANSFERS "" sparse dense
    for form in sparse dense; do
        check "rollout-256-$form" env MINFLOW_CUDA_TRANSFERS=$form "$BIN" bench rollout \
            --device cuda --model models/all-grid-mingru --model models/all-grid-mingru-small-k4 \
            --constraints off --scenes 256 --batch 256 --threads 16 --frames 20
    done
}

agree() { # name log-a log-b [tolerance]: the first-epoch loss (last column of the mingru line)
    # of two bench train logs agrees to the tolerance (default 1e-5) of itself
    check "$1" awk -v tol="${4:-1e-5}" 'FNR == 1 { f++ } $1 == "mingru" && $NF ~ /^[0-9]/ { loss[f] = $NF }
        END { d = loss[1] - loss[2]; if (d < 0) d = -d
              if (!(1 in loss) || !(2 in loss) || d > tol * loss[1]) {
                  print "first-epoch losses differ:", loss[1], loss[2]; exit 1 }
              print "first-epoch losses agree:", loss[1], loss[2] }' "$2" "$3"
}

fused() { # docs/train_speed.md, "Training the grid architecture on a GPU" and docs/kernels.md
    nvidia-smi --query-gpu=name,driver_version --format=csv
    grid_forms MINFLOW_CUDA_ADAM adam- kernel composed
    for b in 16 32; do
        agree "grid-adam-$b-agree" "$OUT/grid-adam-kernel-$b.log" "$OUT/grid-adam-composed-$b.log"
    done
    local models=()
    for m in models/*/; do [ -f "$m/model.json" ] && models+=(--model "${m%/}"); done
    for conv in implicit im2col; do
        check "rollout-256-$conv" env MINFLOW_CUDA_CONV=$conv "$BIN" bench rollout --device cuda \
            "${models[@]}" --constraints off --scenes 256 --batch 256 --threads 16 --frames 20
        check "eval-gpu-$conv" env MINFLOW_CUDA_CONV=$conv "$BIN" eval --device cuda \
            --model models/all-grid-mingru --model models/all-grid-mingru-small-k4 --data bags \
            --split all --starts 3 --no-render --constraints off --out "$OUT/eval-gpu-$conv"
    done
    tables_agree eval-gpu-agree "$OUT/eval-gpu-implicit" "$OUT/eval-gpu-im2col"
    kernels
}

cudnn() { # docs/train_speed.md: the convolutions through cuDNN against im2col and cuBLAS
    nvidia-smi --query-gpu=name,driver_version --format=csv
    echo "cuDNN: ${CUDNN_LIB:-from the system library path}"
    grid_forms MINFLOW_CUDA_CONV conv- cudnn im2col
    for b in 16 32; do
        # TF32 products round differently in the two forms: agree to 1e-3, not bits.
        agree "grid-conv-$b-agree" "$OUT/grid-conv-cudnn-$b.log" "$OUT/grid-conv-im2col-$b.log" 1e-3
        # Training's weights copied into cuDNN's layout each pass (the form before the
        # transposed passes read the matrix in place): the same step, a different algorithm.
        check "grid-conv-permuted-$b" env MINFLOW_CUDA_CONV=cudnn MINFLOW_CUDNN_FILTER=permuted \
            "$BIN" bench train --arch grid --device cuda --cores mingru --micro-batch "$b" \
            --samples $((8 * b)) --epochs 3 --warmup-epochs 1 --stages
        agree "grid-conv-permuted-$b-agree" "$OUT/grid-conv-cudnn-$b.log" \
            "$OUT/grid-conv-permuted-$b.log" 1e-3
    done
    for conv in cudnn im2col; do
        check "rollout-256-$conv" env MINFLOW_CUDA_CONV=$conv MINFLOW_CALL_STAGES=1 "$BIN" bench \
            rollout --device cuda --model models/all-grid-mingru \
            --model models/all-grid-mingru-small-k4 --constraints off --scenes 256 --batch 256 \
            --threads 16 --frames 20
        check "eval-gpu-$conv" env MINFLOW_CUDA_CONV=$conv "$BIN" eval --device cuda \
            --model models/all-grid-mingru --model models/all-grid-mingru-small-k4 --data bags \
            --split all --starts 3 --no-render --constraints off --out "$OUT/eval-gpu-$conv"
    done
    tables_agree eval-gpu-cudnn-agree "$OUT/eval-gpu-cudnn" "$OUT/eval-gpu-im2col"
}

solver() { # docs/mpm.md, "The solver on a GPU"; docs/speed.md, "At scale"
    if [ ! -x gpu/it ] && [ -f gpu/it.xz ]; then
        python3 -c "import lzma, shutil; shutil.copyfileobj(lzma.open('gpu/it.xz'), open('gpu/it', 'wb'))"
        chmod +x gpu/it
    fi
    check solver-checks gpu/it sim_validation --test-threads 1
    check solver-64 "$BIN" bench sim --device cuda --frames 100 --scenes 1 --threads 16 --batch 256
    check solver-128 "$BIN" bench sim --device cuda --frames 20 --scenes 1 --threads 16 \
        --batch 256 --family multi --grid 128
    check solver-256 "$BIN" bench sim --device cuda --frames 10 --scenes 1 --threads 16 \
        --batch 16 --family multi --grid 256
    for run in a b; do
        "$BIN" simulate --device cuda --family multi --scenes 0..256 --frames 100 \
            --out "$OUT/gpu-$run" >/dev/null 2>&1
    done
    check solver-bags diff <(cd "$OUT/gpu-a" && md5sum *.mcap) <(cd "$OUT/gpu-b" && md5sum *.mcap)
}

projection() { # docs/cuda.md, "The projection on the device"
    if [ ! -x gpu/it ] && [ -f gpu/it.xz ]; then
        python3 -c "import lzma, shutil; shutil.copyfileobj(lzma.open('gpu/it.xz'), open('gpu/it', 'wb'))"
        chmod +x gpu/it
    fi
    check projection-parity gpu/it model_device_projection --nocapture
    # Both families: the host's projection, then the device's.
    for where in host device; do
        for family in multi fluid; do
            check "projection-$family-$where" env MINFLOW_CUDA_PROJECTION=$where "$BIN" \
                bench rollout --device cuda --family $family \
                --model models/all-grid-mingru-small-k4 --model models/all-grid-mingru \
                --model models/all-grid-mingru-small-k4-mixed --model models/all-grid-mingru-rest-mixed \
                --constraints off --constraints on --scenes 256 --batch 256 --threads 16 --frames 100
        done
        check "projection-eval-$where" env MINFLOW_CUDA_PROJECTION=$where "$BIN" eval \
            --device cuda --model models/all-grid-mingru-small-k4 --model models/all-grid-mingru \
            --data bags --split all --starts 3 --no-render --out "$OUT/projection-eval-$where"
        # Training through the projection: samples/s and losses in metrics.csv.
        [ -d "$OUT/projection-data" ] || "$BIN" simulate --device cuda --family multi \
            --scenes 0..12 --frames 120 --out "$OUT/projection-data" >/dev/null 2>&1
        check "projection-train-$where" env MINFLOW_CUDA_PROJECTION=$where "$BIN" train \
            --data "$OUT/projection-data" --out "$OUT/projection-train-$where" \
            --init-from models/all-grid-mingru-small-k4 --unet-width 16 --levels 3 --bundle 4 \
            --model mingru --reference none --constraints on --epochs 2 --samples-per-epoch 320 \
            --device cuda --seed 3 --val-starts 1
    done
    tables_agree projection-eval-agree "$OUT/projection-eval-device" "$OUT/projection-eval-host"
}

tables_agree() { # name dir-a dir-b: every eval table.csv under the two folders within 1e-3
    check "$1" "$PY" - "$2" "$3" <<'PY'
import csv, glob, os, sys
worst, tables = 0.0, 0
a, b = sys.argv[1:3]
for path in sorted(glob.glob(os.path.join(a, "**", "table.csv"), recursive=True)):
    tables += 1
    other = os.path.join(b, os.path.relpath(path, a))
    for ra, rb in zip(csv.reader(open(path)), csv.reader(open(other))):
        for x, y in zip(ra, rb):
            try:
                x, y = float(x), float(y)
            except ValueError:
                continue
            worst = max(worst, abs(x - y) / max(abs(y), 1e-12))
print(f"largest relative difference of the {tables} eval tables: {worst:.2e}")
sys.exit(tables == 0 or worst > 1e-3)
PY
}

for part in "${@:-speed}"; do
    "$part"
done
echo "failed parts: $failed"
exit "$failed"
