"""An independent ROS 2 listener for shoal's `--ros2` publication.

Connects to a Zenoh router with the Python `eclipse-zenoh` client, takes
every sample of a ROS 2 domain the way `rmw_zenoh` lays it out, and decodes
it with `rosbags`' own CDR deserializer and type store (ROS 2 Jazzy
definitions). Checks on the way, each failure listed in the report:

- the key is `<domain>/<topic>/<pkg>::msg::dds_::<Type>_/<RIHS01 hash>` and the
  hash is the one `rosbags` computes for that type;
- every sample carries the 33-byte attachment (sequence from 1, +1 per
  sample, source time, 0x10, a 16-byte GID);
- every topic has a publisher liveliness token (`MP`) naming the same topic,
  type and hash, under a node token (`NN`).

Prints one JSON report on stdout: decoded messages per topic and problems.

    python3 tests/python/ros2_listen.py ENDPOINT DOMAIN SECONDS
"""

import json
import struct
import sys
import threading
import time

import zenoh
from rosbags.typesys import Stores, get_typestore


def ros_name(dds):
    # geometry_msgs::msg::dds_::PoseWithCovarianceStamped_ -> geometry_msgs/msg/PoseWithCovarianceStamped
    parts = dds.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        return None
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def stamp_ns(header):
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def as_json(typename, msg):
    if typename == "geometry_msgs/msg/PoseWithCovarianceStamped":
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        return {
            "stamp_ns": stamp_ns(msg.header),
            "frame_id": msg.header.frame_id,
            "position": [p.x, p.y, p.z],
            "orientation": [q.x, q.y, q.z, q.w],
            "covariance": [float(c) for c in msg.pose.covariance],
        }
    if typename == "tf2_msgs/msg/TFMessage":
        return {
            "transforms": [
                {
                    "stamp_ns": stamp_ns(t.header),
                    "parent": t.header.frame_id,
                    "child": t.child_frame_id,
                    "translation": [t.transform.translation.x, t.transform.translation.y, t.transform.translation.z],
                    "rotation": [t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w],
                }
                for t in msg.transforms
            ]
        }
    if typename == "diagnostic_msgs/msg/DiagnosticArray":
        return {
            "stamp_ns": stamp_ns(msg.header),
            "status": [
                {
                    "level": int(s.level),
                    "name": s.name,
                    "message": s.message,
                    "hardware_id": s.hardware_id,
                    "values": {kv.key: kv.value for kv in s.values},
                }
                for s in msg.status
            ],
        }
    return {"unexpected_type": typename}


def main(endpoint, domain, seconds):
    store = get_typestore(Stores.ROS2_JAZZY)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    lock = threading.Lock()
    samples = []

    def on_sample(sample):
        att = sample.attachment
        with lock:
            samples.append((str(sample.key_expr), sample.payload.to_bytes(), None if att is None else att.to_bytes()))

    tokens = set()

    def on_token(sample):
        if sample.kind == zenoh.SampleKind.PUT:
            with lock:
                tokens.add(str(sample.key_expr))

    report = {"topics": {}, "problems": [], "samples": 0, "tokens": [], "nodes": []}
    with zenoh.open(conf) as session:
        # As rmw_zenoh's graph cache: the tokens alive now, then those declared later.
        live = session.liveliness().declare_subscriber(f"@ros2_lv/{domain}/**", on_token, history=True)
        sub = session.declare_subscriber(f"{domain}/**", on_sample)
        time.sleep(seconds)
        sub.undeclare()
        live.undeclare()
    with lock:
        tokens = sorted(tokens)
    report["tokens"] = tokens
    publishers = {}
    for t in tokens:
        chunks = t.split("/")
        if len(chunks) >= 9 and chunks[5] == "NN":
            report["nodes"].append(chunks[8])
        if len(chunks) == 13 and chunks[5] == "MP":
            topic = chunks[9].replace("%", "/")
            publishers[topic] = (chunks[10], chunks[11], chunks[12])

    sequences = {}
    hashes = {}
    for key, payload, att in samples:
        report["samples"] += 1
        chunks = key.split("/")
        if len(chunks) < 4 or chunks[0] != str(domain):
            report["problems"].append(f"{key}: not <domain>/<topic>/<type>/<hash>")
            continue
        dds, rihs = chunks[-2], chunks[-1]
        topic = "/" + "/".join(chunks[1:-2])
        typename = ros_name(dds)
        if typename is None:
            report["problems"].append(f"{key}: type chunk {dds!r} is not a DDS type name")
            continue
        if typename not in hashes:
            hashes[typename] = store.hash_rihs01(typename)
        if rihs != hashes[typename]:
            report["problems"].append(f"{key}: hash {rihs} but rosbags computes {hashes[typename]}")
        if att is None or len(att) != 33 or att[16] != 16:
            report["problems"].append(f"{key}: attachment {None if att is None else len(att)} bytes, not rmw_zenoh's 33")
        else:
            seq, source_ns = struct.unpack_from("<qq", att, 0)
            last = sequences.get(key)
            if last is not None and seq != last + 1:
                report["problems"].append(f"{key}: sequence {seq} after {last}")
            if source_ns <= 0:
                report["problems"].append(f"{key}: source time {source_ns}")
            sequences[key] = seq
        pub = publishers.get(topic)
        if pub is None:
            report["problems"].append(f"{topic}: samples but no MP liveliness token")
        elif pub[0] != dds or pub[1] != rihs or not pub[2]:
            report["problems"].append(f"{topic}: token says {pub}, key says {dds} {rihs}")
        try:
            msg = store.deserialize_cdr(payload, typename)
        except Exception as e:  # noqa: BLE001 - every decoding failure is a finding
            report["problems"].append(f"{key}: rosbags cannot decode: {e}")
            continue
        entry = report["topics"].setdefault(topic, {"type": typename, "messages": []})
        entry["messages"].append(as_json(typename, msg))
    if not report["nodes"]:
        report["problems"].append("no ROS 2 node liveliness token")
    json.dump(report, sys.stdout)


if __name__ == "__main__":
    if len(sys.argv) != 4:
        raise SystemExit(__doc__)
    main(sys.argv[1], int(sys.argv[2]), float(sys.argv[3]))
