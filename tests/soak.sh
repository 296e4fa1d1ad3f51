#!/usr/bin/env bash
# Issue 35's long soak: `replay --loop` at 62.5 Hz into `node` and `record` over zenoh for
# SECS seconds (default 600), the same test CI runs for 20 s (tests/it/soak.rs). Prints the
# resident memory of each process at the end of the warm-up and its largest value after,
# the end-to-end latency p50/p99 of the first and last third, and the frame counts; exits
# non-zero if a frame was dropped, memory grew more than 10 % after the warm-up, or the
# last third's p99 is above 1.5x the first's plus 5 ms.
#
#   tests/soak.sh            10 minutes
#   tests/soak.sh 120        2 minutes
set -eu
cd "$(dirname "$0")/.."
export MINFLOW_SOAK_SECS=${1:-600}
exec cargo test --release --test it soak::soak_replay_loop_into_node_and_record -- --exact --nocapture
