#!/usr/bin/env bash
# The surrogate node on a GPU machine (docs/scale.md, "On one H100"): `bench node`'s streams
# table and the node's wall time by stage (its closing `time:` line), for the accurate and
# the small bundled model, at the issue's load (256 streams at 62.5 Hz) and at a load a
# node holds (256 streams at 4 Hz). CI has no GPU and does not run this. From the
# repository root, with a `cuda` build of the full `minflow` binary (`minflow-cuda` has no
# `bench node`) as gpu/minflow or gpu/minflow.xz:
#
#   BIN=gpu/minflow tests/gpu/node.sh [MODEL...]
set -uo pipefail
BIN=${BIN:-gpu/minflow}
. "$(dirname "$0")/common.sh"
models=("$@")
[ ${#models[@]} -gt 0 ] || models=(all-grid-mingru all-grid-mingru-small-k4)
for m in "${models[@]}"; do
    for rate in 62.5 4; do
        "$BIN" bench node --device cuda --model "models/$m" --streams 256 --rate "$rate" \
            --max-batch 64,256 --warm-up 12 --seconds 12 2>&1 | grep -v '^bench node:'
    done
done
