#!/usr/bin/env bash
# A grid call's per-particle frames as one kernel (src/ops/cuda/net/frames.rs) against their
# tensor form (MINFLOW_CUDA_FRAMES=composed), in one binary: each form's cost a scene-frame
# beside the GPU solver's and its avg20 MSE (the same rollouts: the two forms' MSE agree to
# float noise), for the demo model and the scale model at 2,500 particles (256 scenes a
# call), 10,000 (--grid 128) and 40,000 (--grid 256, 16 a call), the projection on. BASE, a
# second binary (an earlier build), is timed the same way after them. From the repository
# root, with gpu/minflow-cuda built with `--features cuda` (plain or as gpu/minflow-cuda.xz);
# CI has no GPU and does not run this.
set -uo pipefail
export CUDA_PATH=${CUDA_PATH:-/usr/local/cuda}
unpack() {
    if [ ! -x "$1" ] && [ -f "$1.xz" ]; then
        python3 -c "import lzma, shutil; shutil.copyfileobj(lzma.open('$1.xz'), open('$1', 'wb'))"
        chmod +x "$1"
    fi
}
BIN=${BIN:-gpu/minflow-cuda}
unpack "$BIN"
# MODELS ("--model DIR ..."): the models timed, by default the demo's former and the scale one.
read -r -a MODELS <<<"${MODELS:---model models/all-grid-mingru-small-k4-mixed \
    --model models/scale-grid-mingru-small-k4}"
SIZES=${SIZES:-"--scenes 256 --batch 256|--grid 128 --scenes 256 --batch 256|--grid 256 --scenes 16 --batch 16"}
IFS='|' read -r -a ALL <<<"$SIZES"
run() {
    local bin=$1 form=$2 sizes=$3
    echo "== $bin MINFLOW_CUDA_FRAMES=$form $sizes"
    # shellcheck disable=SC2086
    MINFLOW_CUDA_FRAMES=$form "$bin" bench rollout --device cuda "${MODELS[@]}" --frames 20 \
        --threads 16 $sizes ${FLAGS:-} 2>&1 | grep --line-buffered -v "^\s*$"
}
for sizes in "${ALL[@]}"; do
    run "$BIN" kernel "$sizes"
    run "$BIN" composed "$sizes"
    if [ -n "${BASE:-}" ]; then
        unpack "$BASE"
        run "$BASE" kernel "$sizes"
    fi
done
