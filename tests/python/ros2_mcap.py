"""An independent reader of shoal's ROS 2-profile MCAP logs (`shoal record --profile ros2`).

Reads the file with the reference Python `mcap` reader (chunk CRCs checked),
builds a type store from nothing but the `ros2msg` schemas the file carries
(rosbags' `get_types_from_msg`), checks that each schema describes the same
type as ROS 2 Jazzy's (equal RIHS01 hashes), and decodes every message with
rosbags' CDR deserializer. Prints the same JSON report as `ros2_listen.py`.

    python3 tests/python/ros2_mcap.py LOG.mcap
"""

import json
import os
import sys

from mcap.reader import make_reader
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ros2_listen import as_json  # noqa: E402


def main(path):
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    store = get_typestore(Stores.EMPTY)
    report = {"topics": {}, "problems": [], "samples": 0, "profile": None}
    registered = set()
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        report["profile"] = reader.get_header().profile
        for schema, channel, message in reader.iter_messages():
            report["samples"] += 1
            if channel.message_encoding != "cdr" or schema is None or schema.encoding != "ros2msg":
                report["problems"].append(
                    f"{channel.topic}: encoding {channel.message_encoding!r}, schema {None if schema is None else schema.encoding!r}"
                )
                continue
            if schema.name not in registered:
                store.register(get_types_from_msg(schema.data.decode(), schema.name))
                registered.add(schema.name)
                mine, theirs = store.hash_rihs01(schema.name), jazzy.hash_rihs01(schema.name)
                if mine != theirs:
                    report["problems"].append(f"{schema.name}: the file's definition hashes to {mine}, Jazzy's to {theirs}")
            try:
                msg = store.deserialize_cdr(message.data, schema.name)
            except Exception as e:  # noqa: BLE001 - every decoding failure is a finding
                report["problems"].append(f"{channel.topic}: rosbags cannot decode: {e}")
                continue
            entry = report["topics"].setdefault(channel.topic, {"type": schema.name, "messages": []})
            entry["messages"].append(as_json(schema.name, msg))
    json.dump(report, sys.stdout)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    main(sys.argv[1])
