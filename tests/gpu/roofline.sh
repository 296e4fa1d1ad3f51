#!/usr/bin/env bash
# The roofline of a network call (docs/speed.md, "Roofline by part"; CI has no GPU and does not
# run this): `bench rollout --stages` for the demo model and the scale model at 2,500
# particles (256 scenes a call), 10,000 (--grid 128, 256 a call) and 40,000 (--grid 256, 16 a
# call). From the repository root, with gpu/minflow-cuda built with `--features cuda` (plain
# or as gpu/minflow-cuda.xz). PEAKS: the GPU's limits (default H200's: 4800 GB/s, 495 TF32
# TFLOP/s; an H100 SXM: "--peak-gbs 3350").
set -uo pipefail
BIN=${BIN:-gpu/minflow-cuda}
export CUDA_PATH=${CUDA_PATH:-/usr/local/cuda}
if [ ! -x "$BIN" ] && [ -f "$BIN.xz" ]; then
    python3 -c "import lzma, shutil; shutil.copyfileobj(lzma.open('$BIN.xz'), open('$BIN', 'wb'))"
    chmod +x "$BIN"
fi
MODELS=(--model models/all-grid-mingru-small-k4-mixed --model models/scale-grid-mingru-small-k4)
for sizes in "--scenes 256 --batch 256" "--grid 128 --scenes 256 --batch 256" \
    "--grid 256 --scenes 16 --batch 16"; do
    echo "== $sizes"
    # shellcheck disable=SC2086
    "$BIN" bench rollout --device cuda "${MODELS[@]}" --stages --frames 20 --threads 16 \
        $sizes ${PEAKS:-} 2>&1 | grep -v "^\s*$"
done
