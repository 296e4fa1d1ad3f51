"""Reads the foxglove.PointCloud messages of an MCAP bag (`minflow record --points`) the way
Foxglove does: by schema name and encoding, decoded with Foxglove's published protobuf
schemas (foxglove-schemas-protobuf). Prints one JSON object: per points topic, the schema,
the message encoding, and per message the point count and log time.

Usage: read_points.py BAG...
Exit codes: 0 ok, 1 error, 3 a package is missing.
"""

import json
import sys

try:
    from mcap.reader import make_reader
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
except ImportError as e:
    print(f"No module named {e.name}", file=sys.stderr)
    sys.exit(3)


def main():
    topics = {}
    for path in sys.argv[1:]:
        with open(path, "rb") as f:
            for schema, channel, message in make_reader(f).iter_messages():
                if schema is None or schema.name != "foxglove.PointCloud":
                    continue
                entry = topics.setdefault(channel.topic, {
                    "schema_encoding": schema.encoding,
                    "message_encoding": channel.message_encoding,
                    "messages": [],
                })
                cloud = PointCloud()
                cloud.ParseFromString(message.data)
                entry["messages"].append({
                    "points": len(cloud.data) // cloud.point_stride,
                    "log_time": message.log_time,
                })
    print(json.dumps(topics))


if __name__ == "__main__":
    main()
