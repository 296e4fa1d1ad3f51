"""Writes a small LagrangeBench-style dataset with h5py (the reference HDF5 library) for
tests/it/interop_import_h5py.rs: metadata.json, train.h5 (group 00000) and valid.h5 (group
00007), positions [T, N, 2] float64 stored chunked and gzip-compressed, as libhdf5 lays them
out, particle_type [N] int32. Periodic in x and y; x wraps across the boundary.

Usage: python write_lagrangebench.py DIR T N
"""
import json
import sys

import h5py
import numpy as np

out, T, N = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
meta = {
    "dim": 2,
    "dt": 0.01,
    "write_every": 2,
    "bounds": [[0.0, 1.0], [0.0, 0.5], [0.0, 0.0]],
    "periodic_boundary_conditions": [True, True, True],
}
with open(f"{out}/metadata.json", "w") as f:
    json.dump(meta, f)

t = np.arange(T, dtype=np.float64)[:, None]
u = np.arange(N, dtype=np.float64)[None, :] / N
# Must match `h5py_position` in the Rust test.
position = np.stack([(0.5 + 0.3 * u + 0.07 * t) % 1.0, 0.25 + 0.1 * u + 0.001 * t], axis=-1)
types = (np.arange(N) % 2).astype(np.int32)
for split, group in [("train", "00000"), ("valid", "00007")]:
    with h5py.File(f"{out}/{split}.h5", "w") as h5:
        g = h5.create_group(group)
        g.create_dataset("position", data=position, chunks=(4, N, 2), compression="gzip")
        g.create_dataset("particle_type", data=types)
