#!/usr/bin/env python3
"""Reads a session's MCAP export with the `mcap` library (Foxglove's reference reader)
and prints what it holds as one JSON object: per topic its schema, encodings and
message count, and the decoded poses, tracking states, transform and point cloud.
Used by tests/tests/export.rs. Usage: check-mcap.py FILE"""

import base64
import json
import struct
import sys

from mcap.reader import make_reader


def main():
    topics, poses, states, trajectory, tf, cloud, images = {}, [], [], None, None, None, []
    with open(sys.argv[1], "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        for schema, channel, message in reader.iter_messages():
            t = topics.setdefault(channel.topic, {"schema": schema.name, "schema_encoding": schema.encoding,
                                                  "message_encoding": channel.message_encoding, "messages": 0})
            t["messages"] += 1
            body = json.loads(message.data)
            if channel.topic == "/pose":
                p = body["pose"]
                poses.append({"log_time": message.log_time, "frame_id": body["frame_id"],
                              "translation": [p["position"][k] for k in "xyz"], "rotation_xyzw": [p["orientation"][k] for k in "xyzw"]})
            elif channel.topic == "/tracking_state":
                states.append(body)
            elif channel.topic == "/trajectory":
                trajectory = len(body["poses"])
            elif channel.topic == "/tf":
                tf = body
            elif channel.topic == "/keyframes":
                jpeg = base64.b64decode(body["data"])
                images.append({"format": body["format"], "bytes": len(jpeg), "jpeg": jpeg[:2] == b"\xff\xd8" and jpeg[-2:] == b"\xff\xd9",
                               "log_time": message.log_time})
            elif channel.topic == "/map":
                data = base64.b64decode(body["data"])
                stride = body["point_stride"]
                fields = {f["name"]: (f["offset"], f["type"]) for f in body["fields"]}
                n = len(data) // stride
                classes = {struct.unpack_from("<H", data, i * stride + fields["class"][0])[0] for i in range(n)}
                x0 = struct.unpack_from("<fff", data, 0) if n else None
                cloud = {"points": n, "stride": stride, "remainder": len(data) % stride, "fields": sorted(fields),
                         "classes": len(classes), "first": x0, "frame_id": body["frame_id"]}
        metadata = [m.metadata for m in reader.iter_metadata()]
    print(json.dumps({"topics": topics, "poses": poses, "states": len(states), "first_state": states[0] if states else None,
                      "trajectory": trajectory, "tf": tf, "images": images, "cloud": cloud, "metadata": metadata,
                      "channels_in_summary": len(summary.channels) if summary else 0}))


if __name__ == "__main__":
    main()
