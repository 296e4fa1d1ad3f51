#!/usr/bin/env bash
# Prints a results table on this machine: every run folder under models/ against the
# persist and constvel baselines on the bundled bags (held-out scenes: the models were
# trained on `simulate --seed 1` data), and each model's step against the simulator's frame.
# Each column names the command it comes from; the table is what those commands printed.
# (The README's Results table is measured on 16 unseen scenes instead; its commands are
# under it, and docs/results.md says how each column was made.)
#
#   tools/readme_table.sh                          # builds and runs target/release/minflow
#   MINFLOW=/path/to/minflow tools/readme_table.sh
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ -z "${MINFLOW:-}" ]]; then
    cargo build --release -q
    MINFLOW="${CARGO_TARGET_DIR:-target}/release/minflow"
fi
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
args=()
for m in models/*/; do
    [[ -f "$m/model.json" ]] && args+=(--model "${m%/}")
done

# Accuracy: eval's Average row (avg20, f20) per column.
"$MINFLOW" eval "${args[@]}" --data bags --split all --no-render --out "$out/eval" >/dev/null 2>&1
# Cost: the model's step on one scene (p50 ms), and the simulator's multi frame on all cores.
"$MINFLOW" bench node "${args[@]}" --skip-node --batch 1 2>/dev/null >"$out/bench.txt"
"$MINFLOW" bench sim 2>/dev/null >"$out/sim.txt"

sim_ms=$(awk '$1 == "multi" { ms = $6 } END { print ms }' "$out/sim.txt")
threads=$(awk '$1 == "multi" { t = $5 } END { print t }' "$out/sim.txt")
echo "| model | avg20 | f20 | avg20 / persist | step p50, ms | step / solver frame |"
echo "| --- | ---: | ---: | ---: | ---: | ---: |"
awk -F, -v bench="$out/bench.txt" -v sim="$sim_ms" '
    BEGIN {
        while ((getline line < bench) > 0) {
            n = split(line, c, "|")
            gsub(/ /, "", c[2]); gsub(/ /, "", c[3]); gsub(/ /, "", c[4])
            if (n >= 6 && c[3] == "1") step[c[2]] = c[4]
        }
    }
    NR == 1 { for (i = 2; i <= NF; i++) col[$i] = i; next }
    $1 == "Average" {
        for (k in col) {
            split(k, p, "_"); name = substr(k, length(p[1]) + 2)
            if (p[1] == "avg20") avg[name] = $col[k]
            if (p[1] == "f20") f20[name] = $col[k]
            if (p[1] == "avg20") order[col[k]] = name
        }
    }
    END {
        for (i = 2; i in order || i < 100; i++) {
            if (!(i in order)) continue
            name = order[i]
            cost = (name in step) ? sprintf("%.1f | %.1fx", step[name], step[name] / sim) : "- | -"
            printf "| `%s` | %.2e | %.2e | %.3f | %s |\n", name, avg[name], f20[name], avg[name] / avg["persist"], cost
        }
    }' "$out/eval/table.csv"
echo "| MLS-MPM solver (\`bench sim\`, multi, $threads threads) | | | | $sim_ms | 1x |"
