"""A Foxglove WebSocket client for tests/it/viz_foxglove.rs. It offers the protocol under both
its names, `foxglove.sdk.v1` (what the Foxglove SDK's server and the current Foxglove app
speak) and `foxglove.websocket.v1` (the same protocol's name before the SDK; older clients
offer only that one), as the Foxglove app does, and reports which one the server chose.

Connects to URL, waits for the advertisement of TOPIC, subscribes to it, receives COUNT
messages, decodes each with Foxglove's published protobuf schemas (foxglove-schemas-protobuf)
and prints one JSON object (and the line "subscribed" on stderr once it asked for the topic): the
negotiated subprotocol, the advertised channel and, per message, the point count, the
stride, the field names, the frame id, the timestamp and the first point's values.

Usage: foxglove_client.py URL TOPIC COUNT TIMEOUT_S
Exit codes: 0 ok, 1 protocol or timeout error, 3 a package is missing.
"""

import asyncio
import json
import struct
import sys

try:
    import websockets
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
except ImportError as e:  # the Rust test turns this into an install hint
    print(f"No module named {e.name}", file=sys.stderr)
    sys.exit(3)

MESSAGE_DATA = 0x01


def first_point(cloud):
    """x, y, error, red, green, blue, alpha, material of point 0, by the advertised fields."""
    fields = {f.name: f.offset for f in cloud.fields}
    data = cloud.data
    x, y, error = (struct.unpack_from("<f", data, fields[k])[0] for k in ("x", "y", "error"))
    rgbam = [data[fields[k]] for k in ("red", "green", "blue", "alpha", "material")]
    return [x, y, error] + rgbam


async def run(url, topic, count, timeout):
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                                  max_size=None) as ws:
        channel = None
        while channel is None:
            msg = json.loads(await ws.recv())
            if msg.get("op") == "advertise":
                channel = next((c for c in msg["channels"] if c["topic"] == topic), None)
        await ws.send(json.dumps({"op": "subscribe",
                                  "subscriptions": [{"id": 7, "channelId": channel["id"]}]}))
        print("subscribed", file=sys.stderr, flush=True)
        frames = []
        while len(frames) < count:
            msg = await ws.recv()
            if isinstance(msg, str) or msg[0] != MESSAGE_DATA:
                continue
            sub_id, log_time = struct.unpack_from("<IQ", msg, 1)
            assert sub_id == 7, sub_id
            cloud = PointCloud()
            cloud.ParseFromString(msg[13:])
            frames.append({
                "points": len(cloud.data) // cloud.point_stride,
                "bytes": len(cloud.data),
                "stride": cloud.point_stride,
                "fields": [f.name for f in cloud.fields],
                "frame_id": cloud.frame_id,
                "stamp_ns": cloud.timestamp.seconds * 10**9 + cloud.timestamp.nanos,
                "first": first_point(cloud),
            })
        print(json.dumps({
            "subprotocol": ws.subprotocol,
            "channel": {k: channel[k] for k in ("topic", "encoding", "schemaName",
                                                 "schemaEncoding")},
            "frames": frames,
        }))


def main():
    url, topic, count, timeout = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    asyncio.run(asyncio.wait_for(run(url, topic, count, timeout), timeout))


if __name__ == "__main__":
    main()
