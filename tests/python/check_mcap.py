"""Independent check of a shoal MCAP log with the reference Python readers.

Reads every message with the `mcap` reader (chunk CRCs validated), decodes
every protobuf (Foxglove) channel with `mcap-protobuf-support`'s decoder,
built only from the schema records in the file, checks the decoded values
(times, unit quaternions, PNG images, log levels, scene entities) and that
nothing in the bytes went undecoded, checks the raw shoal envelopes, and
prints a JSON report on stdout.

    python3 tests/python/check_mcap.py LOG.mcap
"""

import json
import math
import sys

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def fail(topic, why):
    raise SystemExit(f"{topic}: {why}")


def check_time(topic, t):
    """A google.protobuf.Timestamp (Foxglove's time), as nanoseconds."""
    if t.seconds < 0 or not (0 <= t.nanos < 1_000_000_000):
        fail(topic, f"time {t.seconds} s {t.nanos} ns out of range")
    return t.seconds * 1_000_000_000 + t.nanos


def check_quaternion(topic, q):
    n = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    if abs(n - 1.0) > 1e-6:
        fail(topic, f"quaternion norm {n}")


def check(topic, name, m, report):
    """Value checks per Foxglove schema; returns a short summary for the report."""
    if name == "foxglove.FrameTransforms":
        for tf in m.transforms:
            check_time(topic, tf.timestamp)
            if not tf.parent_frame_id or not tf.child_frame_id:
                fail(topic, "transform without frame names")
            check_quaternion(topic, tf.rotation)
    elif name == "foxglove.PosesInFrame":
        stamp = check_time(topic, m.timestamp)
        if not m.frame_id:
            fail(topic, "poses without a frame")
        for p in m.poses:
            check_quaternion(topic, p.orientation)
        samples = report["poses"].setdefault(topic, [])
        if len(samples) < 5:
            samples.append(
                {
                    "stamp_ns": stamp,
                    "frame_id": m.frame_id,
                    "positions": [[p.position.x, p.position.y, p.position.z] for p in m.poses],
                }
            )
    elif name == "foxglove.Log":
        check_time(topic, m.timestamp)
        if m.level not in (1, 2, 3, 4, 5) or not m.message or not m.name:
            fail(topic, f"log line level {m.level} message {m.message!r} name {m.name!r}")
    elif name == "foxglove.SceneUpdate":
        for e in m.entities:
            check_time(topic, e.timestamp)
            if not e.id or not e.frame_id:
                fail(topic, "scene entity without id or frame")
            for prim in list(e.cylinders) + list(e.spheres):
                check_quaternion(topic, prim.pose.orientation)
                if min(prim.size.x, prim.size.y, prim.size.z) < 0:
                    fail(topic, "negative primitive size")
    elif name == "foxglove.CompressedImage":
        check_time(topic, m.timestamp)
        if m.format != "png" or m.data[:8] != PNG_MAGIC:
            fail(topic, "not a PNG image")
        report["png_images"] += 1
    elif name == "foxglove.ImageAnnotations":
        for pa in m.points:
            check_time(topic, pa.timestamp)
            if len(pa.points) == 0:
                fail(topic, "points annotation without points")
        for ta in m.texts:
            if not ta.text:
                fail(topic, "empty text annotation")
    else:
        fail(topic, f"unexpected Foxglove schema {name}")


def main(path):
    report = {
        "messages": 0,
        "decoded_per_schema": {},
        "png_images": 0,
        "poses": {},
        "wire_channels": {},
        "metadata": {},
        "attachments": [],
    }
    factory = DecoderFactory()
    decoders = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        if summary is None:
            raise SystemExit(f"{path}: no summary section")
        for schema, channel, message in reader.iter_messages():
            report["messages"] += 1
            if channel.message_encoding == "protobuf":
                if schema is None or schema.encoding != "protobuf":
                    fail(channel.topic, "protobuf channel without a protobuf schema")
                if schema.id not in decoders:
                    decoders[schema.id] = factory.decoder_for("protobuf", schema)
                m = decoders[schema.id](message.data)
                if m.DESCRIPTOR.full_name != schema.name:
                    fail(channel.topic, f"decoded {m.DESCRIPTOR.full_name}, schema {schema.name}")
                # Same fields, same length: nothing in the bytes was unknown to the schema.
                if len(m.SerializeToString()) != len(message.data):
                    fail(channel.topic, "bytes the schema does not describe")
                check(channel.topic, schema.name, m, report)
                counts = report["decoded_per_schema"]
                counts[schema.name] = counts.get(schema.name, 0) + 1
            elif channel.message_encoding == "shoal-envelope":
                if message.data[:4] != b"SHOL":
                    fail(channel.topic, "not a shoal envelope")
                kind = int.from_bytes(message.data[6:8], "little")
                if str(kind) != channel.metadata.get("kind"):
                    fail(channel.topic, f"envelope kind {kind} vs channel {channel.metadata}")
                if schema is None or schema.name != channel.metadata.get("schema"):
                    fail(channel.topic, "schema record and channel metadata disagree")
                report["wire_channels"][channel.topic] = dict(channel.metadata)
            else:
                fail(channel.topic, f"unexpected encoding {channel.message_encoding}")
        if summary.statistics.message_count != report["messages"]:
            raise SystemExit(
                f"statistics say {summary.statistics.message_count} messages, read {report['messages']}"
            )
        for m in reader.iter_metadata():
            report["metadata"][m.name] = dict(m.metadata)
        for a in reader.iter_attachments():
            report["attachments"].append(a.name)
    json.dump(report, sys.stdout)


if __name__ == "__main__":
    main(sys.argv[1])
