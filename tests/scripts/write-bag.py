#!/usr/bin/env python3
"""Writes a TUM RGB-D folder as a ROS 2 recording (rosbag2 with MCAP storage) or, with
--ros1, a ROS 1 bag, the way a ROS camera driver would publish it, for the client's
`mcap:` and `rosbag:` source tests:

  /camera/color/image_raw   sensor_msgs/msg/Image rgb8 (every rgb.txt frame)
  /camera/depth/image_raw   sensor_msgs/msg/Image 32FC1 metres (or 16UC1 mm with --depth-mm)
  /camera/color/camera_info sensor_msgs/msg/CameraInfo, freiburg1's calibration, once per colour frame
  /camera/imu               sensor_msgs/msg/Imu, accelerometer.txt turned into the camera's
                            optical frame (x right, y down, z forward), same frame_id as the images

Stamps are the TUM timestamps. Deterministic: the same folder gives the same file.
Usage: write-bag.py TUM_DIR OUT [--frames N] [--depth-mm] [--ros1]
(OUT is the rosbag2 folder, the .mcap file inside it; with --ros1 the .bag file.)
"""

import argparse
from pathlib import Path

import numpy as np
from PIL import Image as PilImage
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

FRAME_ID = "camera_color_optical_frame"
# TUM freiburg1 (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).
FR1_K = [517.3, 0.0, 318.6, 0.0, 516.5, 255.3, 0.0, 0.0, 1.0]
FR1_D = [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]


def read_list(path):
    rows = []
    for line in path.read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        parts = line.split()
        rows.append((parts[0], parts[1:]))
    return rows


def stamp_ns(text):
    sec, _, frac = text.partition(".")
    return int(sec) * 1_000_000_000 + int((frac + "000000000")[:9])


def main():
    p = argparse.ArgumentParser()
    p.add_argument("tum", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--frames", type=int)
    p.add_argument("--depth-mm", action="store_true", help="16UC1 millimetres instead of 32FC1 metres")
    p.add_argument("--ros1", action="store_true", help="a ROS 1 bag instead of a ROS 2 recording")
    p.add_argument("--kinect-imu", action="store_true",
                   help="/camera/imu in the Kinect's own frame and axes (frame_id imu), as TUM's own bags publish it")
    p.add_argument("--default-camera-info", action="store_true",
                   help="ROS's uncalibrated CameraInfo (fx = fy = 525, the centre, no distortion), as TUM's own bags have")
    a = p.parse_args()
    ts = get_typestore(Stores.ROS1_NOETIC if a.ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]
    Header = T["std_msgs/msg/Header"]

    def header(ns, frame_id=FRAME_ID):
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return Header(seq=0, stamp=stamp, frame_id=frame_id) if a.ros1 else Header(stamp=stamp, frame_id=frame_id)

    rgb = read_list(a.tum / "rgb.txt")[: a.frames]
    depth = read_list(a.tum / "depth.txt")[: a.frames]
    accel = read_list(a.tum / "accelerometer.txt") if (a.tum / "accelerometer.txt").exists() else []
    messages = []  # (stamp, topic, message)
    for t, (name,) in rgb:
        ns = stamp_ns(t)
        img = np.asarray(PilImage.open(a.tum / name).convert("RGB"), dtype=np.uint8)
        h, w, _ = img.shape
        messages.append((ns, 0, "/camera/color/image_raw", T["sensor_msgs/msg/Image"](
            header=header(ns), height=h, width=w, encoding="rgb8", is_bigendian=0, step=3 * w,
            data=img.reshape(-1).copy())))
        Roi = T["sensor_msgs/msg/RegionOfInterest"]
        k, d = (([525.0, 0.0, (w - 1) / 2, 0.0, 525.0, (h - 1) / 2, 0.0, 0.0, 1.0], [0.0] * 5) if a.default_camera_info
                else (FR1_K, FR1_D))
        matrices = {"d": np.array(d), "k": np.array(k), "r": np.eye(3).reshape(-1),
                    "p": np.array([k[0], 0, k[2], 0, 0, k[4], k[5], 0, 0, 0, 1, 0], dtype=float)}
        if a.ros1:  # ROS 1 spells them D, K, R, P
            matrices = {k.upper(): v for k, v in matrices.items()}
        messages.append((ns, 1, "/camera/color/camera_info", T["sensor_msgs/msg/CameraInfo"](
            header=header(ns), height=h, width=w, distortion_model="plumb_bob", binning_x=0, binning_y=0,
            roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False), **matrices)))
    for t, (name,) in depth:
        ns = stamp_ns(t)
        raw = np.asarray(PilImage.open(a.tum / name), dtype=np.uint16)  # 1/5000 m
        h, w = raw.shape
        if a.depth_mm:
            data, enc, step = np.round(raw.astype(np.float64) / 5.0).astype("<u2").view(np.uint8).reshape(-1), "16UC1", 2 * w
        else:
            data, enc, step = (raw.astype(np.float64) / 5000.0).astype("<f4").view(np.uint8).reshape(-1), "32FC1", 4 * w
        messages.append((ns, 2, "/camera/depth/image_raw", T["sensor_msgs/msg/Image"](
            header=header(ns), height=h, width=w, encoding=enc, is_bigendian=0, step=step, data=data.copy())))
    Vector3, Quaternion = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    for t, values in accel:
        ns = stamp_ns(t)
        x, y, z = (float(v) for v in values[:3])
        if not a.kinect_imu:
            x, y = -x, -y  # the camera's optical frame
        messages.append((ns, 3, "/camera/imu", T["sensor_msgs/msg/Imu"](
            header=header(ns, "imu" if a.kinect_imu else FRAME_ID), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.full(9, -1.0),
            angular_velocity=Vector3(x=0.0, y=0.0, z=0.0), angular_velocity_covariance=np.full(9, -1.0),
            linear_acceleration=Vector3(x=x, y=y, z=z), linear_acceleration_covariance=np.zeros(9))))
    messages.sort(key=lambda m: (m[0], m[1]))
    if a.ros1:
        writer = Writer1(a.out)
        serialize = ts.serialize_ros1
    else:
        writer = Writer(a.out, version=9, storage_plugin=StoragePlugin.MCAP)
        serialize = ts.serialize_cdr
    with writer:
        conns = {}
        for topic, kind in [("/camera/color/image_raw", "sensor_msgs/msg/Image"), ("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo"),
                            ("/camera/depth/image_raw", "sensor_msgs/msg/Image"), ("/camera/imu", "sensor_msgs/msg/Imu")]:
            conns[topic] = writer.add_connection(topic, kind, typestore=ts)
        for ns, _, topic, msg in messages:
            writer.write(conns[topic], ns, serialize(msg, msg.__msgtype__))


if __name__ == "__main__":
    main()
