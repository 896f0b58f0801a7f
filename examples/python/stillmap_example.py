#!/usr/bin/env python3
"""A small stillmap client: lists the sessions, follows one robot's poses and saves
a tile of its map.

The gRPC stubs are generated from the repository's proto/stillmap.proto with
grpcio-tools at start-up (into a temporary folder), so they always match the server
they were built with. HTTP (the map's extent) uses the standard library only.

    python3 -m venv .venv && .venv/bin/pip install -r examples/python/requirements.txt
    .venv/bin/python examples/python/stillmap_example.py --grpc localhost:50051 \
        --http http://localhost:8080 --poses 10 --tile tile.png

It prints one JSON object: the sessions, the poses it received and the tile it saved.
Exit code 0, or 1 with one line on stderr.
"""

import argparse
import atexit
import importlib
import json
import math
import os
import shutil
import sys
import tempfile
import time
import urllib.error
import urllib.request

PROTO_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "proto")


def load_stubs(proto_dir):
    """Generates stillmap_pb2 / stillmap_pb2_grpc from the proto and imports them."""
    from grpc_tools import protoc
    import grpc_tools

    out = tempfile.mkdtemp(prefix="stillmap-stubs-")
    atexit.register(shutil.rmtree, out, ignore_errors=True)
    include = os.path.join(os.path.dirname(grpc_tools.__file__), "_proto")
    code = protoc.main(
        ["protoc", f"-I{proto_dir}", f"-I{include}", f"--python_out={out}", f"--grpc_python_out={out}", "stillmap.proto"]
    )
    if code != 0:
        raise RuntimeError(f"protoc failed on {proto_dir}/stillmap.proto (exit {code})")
    sys.path.insert(0, out)
    return importlib.import_module("stillmap_pb2"), importlib.import_module("stillmap_pb2_grpc")


def http_json(base, path, token):
    request = urllib.request.Request(base.rstrip("/") + path)
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return json.load(response)
    except urllib.error.HTTPError as e:
        body = e.read().decode("utf-8", "replace")
        raise RuntimeError(f"GET {path}: HTTP {e.code} {body}") from None


def tile_at_centre(info, zoom):
    """The tile (x, y) at `zoom` that holds the centre of the map's extent
    (the scheme `GET /api/v1/maps/{id}` states)."""
    bounds = info.get("bounds_xy")
    if not bounds:
        raise RuntimeError(f"session {info['session_id']} has an empty map")
    metres_per_pixel = info["voxel_size_m"] * 2 ** (info["tiles"]["max_zoom"] - zoom)
    size = info["tiles"]["tile_px"] * metres_per_pixel
    cx, cy = (bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2
    return math.floor(cx / size), math.floor(-cy / size)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--grpc", default="localhost:50051", help="the server's gRPC address")
    parser.add_argument("--http", default="http://localhost:8080", help="the server's HTTP base URL")
    parser.add_argument("--token", default=os.environ.get("STILLMAP_TOKEN"), help="a token with the read scope")
    parser.add_argument("--session", help="the session to follow (default: the first connected one)")
    parser.add_argument("--poses", type=int, default=10, help="how many new poses to receive")
    parser.add_argument("--wait", type=float, default=30.0, help="seconds to wait for a connected session")
    parser.add_argument("--zoom", type=int, help="tile zoom (default: two levels above one voxel per pixel)")
    parser.add_argument("--tile", default="tile.png", help="where to save the tile")
    parser.add_argument("--proto", default=PROTO_DIR, help="the folder holding stillmap.proto")
    args = parser.parse_args()

    import grpc

    pb, pb_grpc = load_stubs(args.proto)
    metadata = [("authorization", f"Bearer {args.token}")] if args.token else []
    with grpc.insecure_channel(args.grpc) as channel:
        query = pb_grpc.QueryStub(channel)
        deadline = time.monotonic() + args.wait
        while True:
            sessions = query.ListSessions(pb.ListSessionsRequest(), metadata=metadata, timeout=10).sessions
            live = [s for s in sessions if s.connected and (args.session is None or s.session_id == args.session)]
            if live or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        if not live:
            raise RuntimeError(f"no connected session within {args.wait} s ({len(sessions)} known)")
        session = live[0]

        poses = []
        stream = query.SubscribePoses(pb.SessionRef(session_id=session.session_id), metadata=metadata, timeout=60)
        for p in stream:
            t, q = p.world_from_camera.translation, p.world_from_camera.rotation
            poses.append({"sequence": p.sequence, "translation": [t.x, t.y, t.z], "rotation_xyzw": [q.x, q.y, q.z, q.w]})
            if len(poses) >= args.poses:
                stream.cancel()
                break

        # The map lags the poses by a keyframe or two: wait for something to draw.
        while True:
            info = http_json(args.http, f"/api/v1/maps/{session.session_id}", args.token)
            if info.get("bounds_xy") or time.monotonic() > deadline + args.wait:
                break
            time.sleep(0.2)
        zoom = args.zoom if args.zoom is not None else max(0, info["tiles"]["max_zoom"] - 2)
        x, y = tile_at_centre(info, zoom)
        tile = query.GetMapTile(pb.MapTileRequest(session_id=session.session_id, zoom=zoom, x=x, y=y), metadata=metadata, timeout=30)
        with open(args.tile, "wb") as f:
            f.write(tile.png)

    print(json.dumps({
        "sessions": [{"session_id": s.session_id, "robot_id": s.robot_id, "connected": s.connected} for s in sessions],
        "session_id": session.session_id,
        "poses": poses,
        "tile": {"zoom": zoom, "x": x, "y": y, "bytes": len(tile.png), "etag": tile.etag, "path": args.tile},
    }))


if __name__ == "__main__":
    try:
        main()
    except Exception as e:  # one line, exit 1
        message = e.details() if hasattr(e, "details") and callable(e.details) else str(e)
        print(f"stillmap_example: {message}", file=sys.stderr)
        sys.exit(1)
