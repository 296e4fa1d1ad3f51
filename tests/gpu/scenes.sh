#!/usr/bin/env bash
# Scenes beyond the paper's families on a GPU machine (docs/results.md, "Your own scenes"):
# the shipped models fine-tuned on the paper's scenes plus the `mixed` family, against the
# same fine-tune on the paper's scenes alone at equal time, then scored on held-out scene
# kinds (launch_configs/scenes/heldout/), on unseen scenes of the paper's families and on
# unseen `mixed` scenes, whole scenes and 20-step rollouts. CI has no GPU and does not run
# this. From the repository root, with minflow built with `--features cuda` in gpu/:
#
#   tests/gpu/scenes.sh data MIXED       # seed 1 (training: paper + MIXED mixed scenes, a
#                                        # count or a range such as 800..1200), seed 7
#                                        # (unseen), the held-out scene files
#   tests/gpu/scenes.sh start MINUTES    # the fine-tunes, in the background (ONLY picks:
#                                        # mx-rest, mx-small, pc-rest, mx-small-longN,
#                                        # mx-rest-longN)
#   tests/gpu/scenes.sh wait             # until they have ended
#   tests/gpu/scenes.sh fit              # the new runs' constraints (constraints fit)
#   tests/gpu/scenes.sh eval NAME...     # models (runs/NAME or a path) on the three test
#                                        # sets, h20 and full: OUT/{heldout,unseen,mixed}-h*
#   tests/gpu/scenes.sh pack             # the tables of OUT as OUT/tables.tgz
#
# Environment: OUT (logs and results, default /tmp/minflow-gpu), DATA (default /tmp/data),
# FROM (the models the fine-tunes start from: `parents`, the default, for -rest and
# -small-k4; `mixed` to go on from -rest-mixed and -small-k4-mixed), TRAIN_ONLY=1 (`data`
# makes only the training scenes).
set -uo pipefail
. "$(dirname "$0")/common.sh"
case "${FROM:-parents}" in
parents) suffix= ;;
mixed) suffix=-mixed ;;
*) echo "FROM must be parents or mixed" >&2; exit 2 ;;
esac
SMALL_BASE=(--model mingru --grid 32 --unet-width 16 --levels 3 --reference none --bundle 4)
SMALL=(--init-from "models/all-grid-mingru-small-k4$suffix" "${SMALL_BASE[@]}" --rollout-steps 4)
REST=(--model mingru --init-from "models/all-grid-mingru-rest$suffix" --rest-shape fit
    --rollout-steps 8)

case "${1:-}" in
data)
    range=${2:-500}
    [[ $range == *..* ]] || range="0..$range"
    if [ -n "${TRAIN_ONLY:-}" ]; then
        for family in multi fluid; do
            "$BIN" simulate --family "$family" --seed 1 --jobs "$(nproc)" \
                --out "$DATA/$family" 2>&1 | tail -n 1
        done
    else
        make_data
    fi
    "$BIN" simulate --family mixed --seed 1 --scenes "$range" --jobs "$(nproc)" \
        --out "$DATA/mixed" 2>&1 | tail -n 1
    [ -n "${TRAIN_ONLY:-}" ] && exit 0
    "$BIN" simulate --family mixed --seed 7 --scenes 0..16 --jobs "$(nproc)" \
        --out "$DATA/unseen_mixed" 2>&1 | tail -n 1
    files=()
    for f in launch_configs/scenes/heldout/*.toml; do files+=(--scene-file "$f"); done
    "$BIN" simulate "${files[@]}" --jobs "$(nproc)" --out "$DATA/heldout" 2>&1 | tail -n 4
    ;;
start)
    m=$2
    TRAIN_DATA="$DATA/multi $DATA/fluid $DATA/mixed" start mx-rest "$m" "${REST[@]}"
    TRAIN_DATA="$DATA/multi $DATA/fluid $DATA/mixed" start mx-small "$m" "${SMALL[@]}"
    start pc-rest "$m" "${REST[@]}"
    # The long-horizon loss: -small-k4's fine-tune with LONG_STEPS (12) rollout steps in its
    # loss instead of 4 (three bundled calls of K = 4), from LONG_FROM (default: as mx-small).
    # LONG_DISCOUNT (1) sets --rollout-discount.
    long=${LONG_STEPS:-12}
    TRAIN_DATA="$DATA/multi $DATA/fluid $DATA/mixed" start "mx-small-long$long" "$m" \
        --init-from "${LONG_FROM:-models/all-grid-mingru-small-k4$suffix}" "${SMALL_BASE[@]}" \
        --rollout-steps "$long" --rollout-discount "${LONG_DISCOUNT:-1}"
    # The same long, discounted loss for -rest's fine-tune (from LONG_REST_FROM, default as
    # mx-rest).
    TRAIN_DATA="$DATA/multi $DATA/fluid $DATA/mixed" start "mx-rest-long$long" "$m" \
        --model mingru --init-from "${LONG_REST_FROM:-models/all-grid-mingru-rest$suffix}" \
        --rest-shape fit --rollout-steps "$long" --rollout-discount "${LONG_DISCOUNT:-1}"
    ;;
wait)
    wait_runs
    ;;
fit)
    for run in mx-rest mx-small $(cd runs && ls -d mx-*-long* 2>/dev/null); do
        [ -d "runs/$run" ] || continue
        "$BIN" constraints fit --model "runs/$run" --data "$DATA"/multi "$DATA"/fluid \
            "$DATA"/mixed --max-scenes 80 2>&1 | tail -n 8 &
    done
    wait
    # The paper-only control keeps its parent's fitted constraints.
    [ -d runs/pc-rest ] && python3 - <<'PY'
import json
parent = json.load(open("models/all-grid-mingru-rest/model.json"))["constraints"]
path = "runs/pc-rest/model.json"
meta = json.load(open(path))
meta["constraints"] = parent
json.dump(meta, open(path, "w"), indent=2)
PY
    ;;
eval)
    shift
    model_flags "$@"
    for set in heldout:heldout unseen:unseen mixed:unseen_mixed; do
        tag=${set%%:*}
        dir=$DATA/${set#*:}
        "$BIN" eval "${models[@]}" --device cuda --data "$dir" --split all --starts 5 \
            --horizon 20 --no-render --out "$OUT/$tag-h20" >"$OUT/$tag-h20.log" 2>&1 &
        "$BIN" eval "${models[@]}" --device cuda --data "$dir" --split all --horizon full \
            --out "$OUT/$tag-full" >"$OUT/$tag-full.log" 2>&1 &
    done
    wait
    find "$OUT" -name '*.gif' -delete
    for log in "$OUT"/*-h20.log "$OUT"/*-full.log; do
        echo "== $log"
        tail -n 3 "$log"
    done
    ;;
pack)
    (cd "$OUT" && tar czf tables.tgz --exclude='*.gif' */table.md */table.csv \
        */plausibility.csv */metrics.csv heldout-full/*.png mixed-full/*.png *.log \
        2>/dev/null; ls -la tables.tgz)
    ;;
*)
    sed -n '2,18p' "$0"
    exit 2
    ;;
esac
