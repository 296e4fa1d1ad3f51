#!/usr/bin/env python3
"""Damaged copies of MCAP bags for tests/reliability.sh (issue 16), with what must survive.

usage: damage.py OUT_DIR BAG...

For each source bag: 8 cuts, 8 single flipped bytes and 2 chunk records whose length field is
overwritten, at positions drawn from a fixed seed; then 7 files that are no bag at all. Writes
OUT_DIR/*.mcap and OUT_DIR/manifest.tsv with one line per file:

    name  total  intact  what

`total` is the source's message count, `intact` the messages in chunks the damage did not touch
(each chunk is CRC-checked whole, so a flip inside a chunk record loses that chunk, a cut loses
the chunks it reaches, a flip in the summary, a message index or the footer loses nothing),
and -1 when the file need not be readable (a damaged magic, no bag at all). Chunk boundaries
and per-chunk message counts come from the file's own records (chunk records and the message
index records after each), read here without an MCAP library.
"""

import os
import random
import struct
import sys

MAGIC = b"\x89MCAP0\r\n"
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_DATA_END = 0x0F


def chunks(data):
    """(start, end, messages) of every chunk record, in file order."""
    out = []
    pos = len(MAGIC)
    while pos + 9 <= len(data):
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        end = pos + 9 + length
        if op == OP_CHUNK:
            out.append([pos, end, 0])
        elif op == OP_MESSAGE_INDEX and out:
            (size,) = struct.unpack_from("<I", data, pos + 9 + 2)
            out[-1][2] += size // 16
        elif op == OP_DATA_END:
            break
        pos = end
    return [tuple(c) for c in out]


def main():
    out_dir, sources = sys.argv[1], sys.argv[2:]
    os.makedirs(out_dir, exist_ok=True)
    rng = random.Random(16)
    rows = []

    def emit(name, data, total, intact, what):
        with open(os.path.join(out_dir, name), "wb") as f:
            f.write(data)
        rows.append(f"{name}\t{total}\t{intact}\t{what}")

    for src in sources:
        data = open(src, "rb").read()
        stem = os.path.basename(src)[: -len(".mcap")]
        cs = chunks(data)
        total = sum(c[2] for c in cs)
        for k in range(8):
            cut = rng.randrange(len(MAGIC), len(data))
            intact = sum(m for (s, e, m) in cs if e <= cut)
            emit(f"{stem}.cut{k}.mcap", data[:cut], total, intact, f"cut at {cut} of {len(data)}")
        for k in range(8):
            at = rng.randrange(len(MAGIC), len(data))
            bad = bytearray(data)
            bad[at] ^= rng.randrange(1, 256)
            hit = [m for (s, e, m) in cs if s <= at < e]
            intact = total - sum(hit)
            emit(f"{stem}.flip{k}.mcap", bytes(bad), total, intact, f"byte {at} flipped")
        for k in range(2):
            s, e, m = cs[rng.randrange(len(cs))]
            bad = bytearray(data)
            length = rng.choice([0, 1, 2**63, 2**64 - 1, rng.randrange(2**32)])
            struct.pack_into("<Q", bad, s + 1, length)
            emit(f"{stem}.len{k}.mcap", bytes(bad), total, total - m, f"chunk at {s}: length {length}")
    noise = bytes(rng.randrange(256) for _ in range(10_000))
    first = open(sources[0], "rb").read()
    for name, data in [
        ("empty.mcap", b""),
        ("seven.mcap", MAGIC[:7]),
        ("magic.mcap", MAGIC),
        ("noise.mcap", noise),
        ("magic-noise.mcap", MAGIC + noise),
        ("flipped-magic.mcap", b"\x00" + first[1:]),
        ("two-bags.mcap", first + first),
    ]:
        emit(name, data, 0, -1, "not a bag")
    with open(os.path.join(out_dir, "manifest.tsv"), "w") as f:
        f.write("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
