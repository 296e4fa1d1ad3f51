"""A real ROS 2 node (rclpy + rmw_fastrtps_cpp, the ROS 2 Kilted wheels from PyPI) that talks
to minflow's `--transport ros2` nodes: tests/it/ros2_rclpy.rs and docs/ros2.md.

Needs `minflow_msgs` built from msgs/ into the environment (tests/python/ros2_env.sh).

    ros2_peer.py sub TOPIC --type frame|status|pointcloud2 [--count N] [--timeout S]
                 [--idle S] [--out FILE]
        Subscribes with the default QoS (reliable, volatile, keep last 10), prints
        `ready` once the subscription exists, then stops after N messages, after S seconds
        in all, or after --idle seconds without a message once one arrived. Writes every
        message's serialized bytes (CDR with its 4-byte header) to FILE as records of a
        4-byte little-endian length and the bytes. Prints one JSON line: {"received": n,
        "type_hashes": [the publishers' type hashes when the first message came], ...}.

    ros2_peer.py pub TOPIC --frames FILE [--hz HZ] [--subscribers N] [--timeout S]
        Waits for N matched subscriptions, publishes the serialized ParticleFrames in FILE
        (records as above) at HZ (0: as fast as rclpy goes) with the default QoS, then
        waits (bounded) until every reader acknowledged them. Prints {"published": n}.

Every wait is bounded; exit status 0 on success, 2 on a timeout before the first message or
match, 3 when rclpy or minflow_msgs cannot be imported.
"""

import argparse
import json
import struct
import sys
import time

try:
    import rclpy
    from rclpy.qos import QoSProfile
    from minflow_msgs.msg import ParticleFrame, SurrogateStatus
    from sensor_msgs.msg import PointCloud2
except ImportError as e:  # pragma: no cover - reported to the Rust test
    print(f"import failed: {e}", file=sys.stderr)
    sys.exit(3)

TYPES = {"frame": ParticleFrame, "status": SurrogateStatus, "pointcloud2": PointCloud2}


def default_qos():
    """rmw_qos_profile_default: reliable, volatile, keep last 10."""
    return QoSProfile(depth=10)


def read_records(path):
    with open(path, "rb") as f:
        data = f.read()
    out, at = [], 0
    while at < len(data):
        (n,) = struct.unpack_from("<I", data, at)
        out.append(data[at + 4 : at + 4 + n])
        at += 4 + n
    return out


def spin_until(node, done, deadline):
    while not done() and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)


def sub(args):
    node = rclpy.create_node("minflow_test_sub")
    received = []
    last = [None]

    hashes = []

    def on_message(raw):
        received.append(bytes(raw))
        last[0] = time.monotonic()
        if len(received) == 1:
            # The publishers' REP-2016 type hashes as this rmw sees them (USER_DATA on DDS).
            for info in node.get_publishers_info_by_topic(args.topic):
                hashes.append(str(info.topic_type_hash))

    node.create_subscription(
        TYPES[args.type], args.topic, on_message, default_qos(), raw=True
    )
    print("ready", flush=True)
    deadline = time.monotonic() + args.timeout

    def done():
        if args.count and len(received) >= args.count:
            return True
        return last[0] is not None and time.monotonic() - last[0] > args.idle

    spin_until(node, done, deadline)
    if args.out:
        with open(args.out, "wb") as f:
            for r in received:
                f.write(struct.pack("<I", len(r)))
                f.write(r)
    summary = {"received": len(received), "timed_out": not done(), "type_hashes": hashes}
    if args.type == "pointcloud2" and received:
        from rclpy.serialization import deserialize_message

        cloud = deserialize_message(received[-1], PointCloud2)
        summary["cloud"] = {
            "frame_id": cloud.header.frame_id,
            "width": cloud.width,
            "height": cloud.height,
            "point_step": cloud.point_step,
            "row_step": cloud.row_step,
            "is_dense": cloud.is_dense,
            "fields": [[f.name, f.offset, f.datatype, f.count] for f in cloud.fields],
            "data_len": len(cloud.data),
        }
    if args.type == "status" and received:
        from rclpy.serialization import deserialize_message

        s = deserialize_message(received[-1], SurrogateStatus)
        summary["status"] = {
            "node": s.node,
            "received": s.received,
            "predicted": s.predicted,
            "published": s.published,
        }
    print(json.dumps(summary), flush=True)
    node.destroy_node()
    return 0 if received else 2


def pub(args):
    frames = read_records(args.frames)
    node = rclpy.create_node("minflow_test_pub")
    publisher = node.create_publisher(ParticleFrame, args.topic, default_qos())
    deadline = time.monotonic() + args.timeout
    spin_until(
        node, lambda: publisher.get_subscription_count() >= args.subscribers, deadline
    )
    if publisher.get_subscription_count() < args.subscribers:
        print(json.dumps({"published": 0, "error": "no subscriber"}), flush=True)
        return 2
    # The matched reader's side (its writer proxy) settles a moment after the match.
    time.sleep(0.3)
    start = time.monotonic()
    for i, raw in enumerate(frames):
        if args.hz > 0:
            due = start + i / args.hz
            while time.monotonic() < due:
                time.sleep(min(0.002, max(0.0, due - time.monotonic())))
        publisher.publish(raw)
    acked = publisher.wait_for_all_acked(
        rclpy.duration.Duration(seconds=min(10.0, args.timeout))
    )
    print(json.dumps({"published": len(frames), "acked": acked}), flush=True)
    node.destroy_node()
    return 0


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    s = p.add_subparsers(dest="cmd", required=True)
    a = s.add_parser("sub")
    a.add_argument("topic")
    a.add_argument("--type", choices=sorted(TYPES), default="frame")
    a.add_argument("--count", type=int, default=0)
    a.add_argument("--timeout", type=float, default=60.0)
    a.add_argument("--idle", type=float, default=5.0)
    a.add_argument("--out")
    b = s.add_parser("pub")
    b.add_argument("topic")
    b.add_argument("--frames", required=True)
    b.add_argument("--hz", type=float, default=62.5)
    b.add_argument("--subscribers", type=int, default=1)
    b.add_argument("--timeout", type=float, default=30.0)
    args = p.parse_args()
    rclpy.init()
    try:
        return sub(args) if args.cmd == "sub" else pub(args)
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
