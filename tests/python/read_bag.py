#!/usr/bin/env python3
"""Reads a minflow bag with the Python `mcap` + `mcap-ros2-support` readers and prints a compact
JSON summary on stdout, for tests/bag_python_interop.rs to compare with what it wrote.

Usage: read_bag.py BAG [TOPIC]   (TOPIC defaults to /mpm/frames)

Output: {"profile", "library", "channels": [{"topic", "message_encoding", "schema_name",
"schema_encoding", "metadata_keys"}], "messages": [{"topic", "schema", "log_time",
"publish_time", "sequence", "sec", "nanosec", "frame_id", "scene", "frame_index", "dt",
"n_position", "n_velocity", "n_material", "position_first", "position_last", "velocity_1",
"material_first", "material_last"}]}, messages in file order. float32 values are printed as
the float64 the decoder widens them to, so they round back to the exact float32; a value
that an array is too short to have is null.
Exit status 3 (with a hint on stderr) when the packages are not installed.
"""

import json
import sys

try:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
except ImportError as err:
    print(
        f"{err}: run `python3 -m pip install -r tests/python/requirements.txt`",
        file=sys.stderr,
    )
    sys.exit(3)


def at(values, i: int):
    """values[i], or None when the array is too short."""
    return values[i] if -len(values) <= i < len(values) else None


def summarize(path: str, topic: str) -> dict:
    with open(path, "rb") as stream:
        reader = make_reader(
            stream, validate_crcs=True, decoder_factories=[DecoderFactory()]
        )
        header = reader.get_header()
        summary = reader.get_summary()
        channels = []
        if summary is not None:
            for channel in sorted(summary.channels.values(), key=lambda c: c.id):
                schema = summary.schemas.get(channel.schema_id)
                channels.append(
                    {
                        "topic": channel.topic,
                        "message_encoding": channel.message_encoding,
                        "schema_name": schema.name if schema else "",
                        "schema_encoding": schema.encoding if schema else "",
                        "metadata_keys": sorted(channel.metadata),
                    }
                )
        messages = []
        for schema, channel, message, frame in reader.iter_decoded_messages(
            topics=[topic], log_time_order=False
        ):
            material = list(frame.material)
            messages.append(
                {
                    "topic": channel.topic,
                    "schema": schema.name if schema else "",
                    "log_time": message.log_time,
                    "publish_time": message.publish_time,
                    "sequence": message.sequence,
                    "sec": frame.header.stamp.sec,
                    "nanosec": frame.header.stamp.nanosec,
                    "frame_id": frame.header.frame_id,
                    "scene": frame.scene,
                    "frame_index": frame.frame_index,
                    "dt": frame.dt,
                    "n_position": len(frame.position),
                    "n_velocity": len(frame.velocity),
                    "n_material": len(material),
                    "position_first": at(frame.position, 0),
                    "position_last": at(frame.position, -1),
                    "velocity_1": at(frame.velocity, 1),
                    "material_first": at(material, 0),
                    "material_last": at(material, -1),
                }
            )
    return {
        "profile": header.profile,
        "library": header.library,
        "channels": channels,
        "messages": messages,
    }


def main() -> None:
    if len(sys.argv) not in (2, 3):
        sys.exit(f"usage: {sys.argv[0]} BAG [TOPIC]")
    topic = sys.argv[2] if len(sys.argv) == 3 else "/mpm/frames"
    json.dump(summarize(sys.argv[1], topic), sys.stdout, separators=(",", ":"))
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
