#!/usr/bin/env python3
"""Fleet cost model: CPU time per frame per stage from one `stillmap-client fleet`
report (its server stage times), and the robots a server of C cores holds.

Usage: deploy/fleet-cost-model.py REPORT.json [--rate 30] [--cores 2 8 16 64]
       [--segment-share 1.0] [--gpu-segmentation]  (segmentation on a GPU: its
       time leaves the CPU budget; the letterboxing stays on the CPU, inside it here)

Take the report of a run that did not saturate the machine (e.g. 1 robot at 10 Hz),
so the stage times are the work itself and not time spent waiting for a core.
Per frame, the CPU spends:
  - the tracking path: its leaf stages summed (decode, flow, warp, ego-motion,
    fusion, feature extraction, dense odometry, matching, optimisation, local BA;
    dense odometry runs on a thread beside extraction, so this is CPU time, more
    than the path's wall time `total`);
  - segmentation: the `segmentation` stage times the share of frames segmented;
  - the map pool: (`map_fuse` + `store_commit`) times the share of frames that
    became keyframes.
A server of C cores then sustains C * 1000 / cpu_ms frames/s, that is
C * 1000 / (cpu_ms * rate) robots at `rate` Hz (an upper bound: it assumes the
work spreads over every core, which the per-session order allows only with at
least as many robots as cores).
"""
import argparse
import json
import sys


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("report")
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--cores", type=int, nargs="+", default=[2, 8, 16, 64])
    ap.add_argument("--gpu-segmentation", action="store_true")
    ap.add_argument("--segment-share", type=float, default=None,
                    help="share of frames segmented (default: as in the report; 1.0 = every frame)")
    a = ap.parse_args()
    r = json.load(open(a.report))
    stages = {s["stage"]: s for s in r["server_stages"]}
    if "total" not in stages:
        sys.exit(f"{a.report}: no server stage times (was --http given?)")
    frames = stages["total"]["frames"]
    share = lambda name: stages[name]["frames"] / frames if name in stages else 0.0
    mean = lambda name: stages[name]["mean_ms"] if name in stages else 0.0
    leaves = ["decode_color", "decode_depth", "perception_flow", "perception_warp", "perception_ego_motion",
              "perception_fusion", "track_extract", "track_dense", "track_match", "track_optimize", "track_local_ba"]
    rows = [(name, mean(name), share(name)) for name in leaves] + [
        ("segmentation", mean("segmentation"), a.segment_share if a.segment_share is not None else share("segmentation")),
        ("map fusion", mean("map_fuse"), share("map_fuse")),
        ("store commit", mean("store_commit"), share("store_commit")),
    ]
    print(f"cost model from {a.report} ({frames} frames)\n")
    print("| stage | ms when it runs | share of frames | CPU ms per frame |")
    print("|---|---|---|---|")
    cpu = 0.0
    for name, ms, sh in rows:
        on_gpu = a.gpu_segmentation and name == "segmentation"
        per_frame = 0.0 if on_gpu else ms * sh
        cpu += per_frame
        note = " (GPU)" if on_gpu else ""
        print(f"| {name}{note} | {ms:.1f} | {sh:.2f} | {per_frame:.1f} |")
    print(f"| **total** | | | **{cpu:.1f}** |")
    print(f"(wall time of the tracking path, `total`: {mean('total'):.1f} ms)\n")
    print(f"| cores | frames/s | robots at {a.rate:.0f} Hz |")
    print("|---|---|---|")
    for c in a.cores:
        fps = c * 1000.0 / cpu
        print(f"| {c} | {fps:.0f} | {fps / a.rate:.1f} |")


if __name__ == "__main__":
    main()
