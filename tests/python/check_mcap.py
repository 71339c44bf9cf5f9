"""Independent check of a shoal MCAP log with the reference Python `mcap` reader.

Reads every message with chunk CRCs validated, validates every JSON
(Foxglove) message against the JSON schema embedded in the file, checks the
PNG images and the raw shoal envelopes, and prints a JSON report on stdout.

    python3 tests/python/check_mcap.py LOG.mcap
"""

import base64
import json
import sys

import jsonschema
from mcap.reader import make_reader


def main(path):
    report = {
        "messages": 0,
        "validated_per_schema": {},
        "png_images": 0,
        "wire_channels": {},
        "metadata": {},
        "attachments": [],
    }
    validators = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        if summary is None:
            raise SystemExit(f"{path}: no summary section")
        for schema, channel, message in reader.iter_messages():
            report["messages"] += 1
            if channel.message_encoding == "json":
                if schema is None or schema.encoding != "jsonschema":
                    raise SystemExit(f"{channel.topic}: JSON channel without a jsonschema schema")
                if schema.id not in validators:
                    validators[schema.id] = jsonschema.Draft202012Validator(json.loads(schema.data))
                value = json.loads(message.data)
                validators[schema.id].validate(value)
                counts = report["validated_per_schema"]
                counts[schema.name] = counts.get(schema.name, 0) + 1
                if schema.name == "foxglove.CompressedImage":
                    png = base64.b64decode(value["data"], validate=True)
                    if png[:8] != b"\x89PNG\r\n\x1a\n" or value["format"] != "png":
                        raise SystemExit(f"{channel.topic}: not a PNG image")
                    report["png_images"] += 1
            elif channel.message_encoding == "shoal-envelope":
                if message.data[:4] != b"SHOL":
                    raise SystemExit(f"{channel.topic}: not a shoal envelope")
                kind = int.from_bytes(message.data[6:8], "little")
                if str(kind) != channel.metadata.get("kind"):
                    raise SystemExit(f"{channel.topic}: envelope kind {kind} vs channel {channel.metadata}")
                if schema is None or schema.name != channel.metadata.get("schema"):
                    raise SystemExit(f"{channel.topic}: schema record and channel metadata disagree")
                report["wire_channels"][channel.topic] = dict(channel.metadata)
            else:
                raise SystemExit(f"{channel.topic}: unexpected encoding {channel.message_encoding}")
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
