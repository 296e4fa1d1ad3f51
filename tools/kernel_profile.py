#!/usr/bin/env python3
"""Summarises cubecl's kernel profile: the kernels of one network call or one training step.

cubecl writes, with CUBECL_DEBUG_OPTION=profile-full and CUBECL_DEBUG_LOG=FILE, one line
`| TIME | KERNEL: INFO` per kernel it launched, each timed alone (the GPU synchronised around
it, so the sum overstates the real time; cuBLAS's products are not in it).
`tests/gpu/run.sh kernels` writes two such logs (gzipped). This script cuts the log into
repeats at each launch of a marker kernel (one per call or step), takes one repeat late in
the run (warm: no compilation in its times) and prints its kernels by count and time.

    tools/kernel_profile.py kernels-call256.txt.gz --marker StencilKernel
    tools/kernel_profile.py kernels-train16.txt.gz --marker Im2colKernel --every 68

`--every K` starts a repeat at every K-th marker (a training step of the full-size grid
model at P = 4 runs 68 im2col kernels: 17 convolutions, 4 rollout steps).
"""

import argparse
import collections
import gzip
import re

UNITS = {"ns": 1e-6, "µs": 1e-3, "us": 1e-3, "ms": 1.0, "s": 1e3}


def kernels(path):
    """(milliseconds, short kernel name) per profiled launch, in order."""
    opener = gzip.open if path.endswith(".gz") else open
    rows = []
    with opener(path, "rt", encoding="utf-8", errors="replace") as f:
        for line in f:
            m = re.match(r"^\| ([0-9.]+)(ns|µs|us|ms|s) +\| (.*)$", line)
            if not m:
                continue
            ms = float(m.group(1)) * UNITS[m.group(2)]
            full = m.group(3).split(": ")[0]
            if "cubek_matmul" in full:
                name = "matmul (cubecl)"
            else:
                name = full.split("<")[0].split("::")[-1]
                op = re.search(r"binary::(\w+Op)|unary_float::(\w+)", full)
                if op and ("Binop" in name or "UnaryFloat" in name):
                    name += "/" + (op.group(1) or op.group(2))
            rows.append((ms, name))
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("log", help="CUBECL_DEBUG_LOG file (.gz or plain)")
    p.add_argument("--marker", required=True, help="kernel name that starts each repeat")
    p.add_argument("--every", type=int, default=1, help="markers per repeat")
    p.add_argument("--repeat", type=int, default=-2, help="which repeat (default: second last)")
    p.add_argument("--top", type=int, default=25)
    a = p.parse_args()
    rows = kernels(a.log)
    starts = [i for i, (_, n) in enumerate(rows) if n == a.marker][:: a.every]
    if len(starts) < 2:
        raise SystemExit(f"{a.marker}: {len(starts)} repeats in {len(rows)} kernels")
    bounds = list(zip(starts, starts[1:] + [len(rows)]))
    lo, hi = bounds[a.repeat]
    seg = rows[lo:hi]
    count, time = collections.Counter(), collections.Counter()
    for ms, name in seg:
        count[name] += 1
        time[name] += ms
    total = sum(time.values())
    print(f"repeat {a.repeat} of {len(bounds)}: {len(seg)} kernels, {total:.2f} ms timed alone")
    print("| kernel | launches | ms | share |\n| --- | ---: | ---: | ---: |")
    for name, ms in time.most_common(a.top):
        print(f"| {name} | {count[name]} | {ms:.3f} | {100 * ms / total:.0f} % |")


if __name__ == "__main__":
    main()
