#!/usr/bin/env python3
"""Where the origin-aligned ATE rotation of a TUM trajectory comes from.

    .deps/evo/bin/python3 tracking/tools/rotation_diagnostics.py GROUNDTRUTH EST [EST ...]

(numpy and scipy: the evo virtual environment that `make deps` builds has both.)

For each estimate (TUM format, `timestamp tx ty tz qx qy qz qw`) it prints the
origin-aligned rotation RMSE (degrees) under several readings of the ground truth:

- nearest: the ground-truth pose nearest in time, as evo and `stillmap-client
  eval` associate (the issue's metric);
- interpolated: the ground truth slerped to the frame's exact timestamp;
- world-aligned: the best constant world-side rotation instead of the first
  frame (what the metric would be if it did not hang on one frame);
- hand-eye: est = A · gt · X with both constant rotations fitted; X is the
  rotation between the ground truth's camera frame and the one the estimate
  moves (a camera-side calibration difference);
- floors: a perfect estimate, scored like the metric: with X = identity and
  with the fitted X;
- the correlation of the remaining per-frame error with the ground truth's
  angular speed (rolling shutter and timing errors grow with it).
"""

import sys

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


# The metric's association: the ground-truth pose nearest in time, within 20 ms.
MAX_DIFF_S = 0.02


def load(path):
    data = np.loadtxt(path)
    return data[:, 0], Rotation.from_quat(data[:, 4:8])


def procrustes(matrices):
    """The rotation nearest to the sum of `matrices` (chordal mean)."""
    u, _, vt = np.linalg.svd(sum(matrices))
    return Rotation.from_matrix(u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt)


def rms_deg(rotations):
    return float(np.sqrt(np.mean(rotations.magnitude() ** 2)) * 180.0 / np.pi)


def origin_aligned(gt, est):
    world = gt[0] * est[0].inv()
    return rms_deg(gt.inv() * world * est)


def hand_eye(gt, est):
    """est ≈ A · gt · X: alternating Procrustes fits of A (world) and X (camera)."""
    x = Rotation.identity()
    for _ in range(50):
        a = procrustes([(est[i] * x.inv()).as_matrix() @ gt[i].as_matrix().T for i in range(len(est))])
        x = procrustes([(gt[i].inv() * a.inv() * est[i]).as_matrix() for i in range(len(est))])
    return a, x


def main():
    if len(sys.argv) < 3:
        sys.exit("usage: rotation_diagnostics.py GROUNDTRUTH EST [EST ...]")
    gt_t, gt_r = load(sys.argv[1])
    slerp = Slerp(gt_t, gt_r)
    for path in sys.argv[2:]:
        t, est = load(path)
        index = np.array([int(np.argmin(np.abs(gt_t - s))) for s in t])
        # Frames the metric cannot associate, or outside the ground truth's span, are left out.
        keep = (np.abs(gt_t[index] - t) <= MAX_DIFF_S) & (t >= gt_t[0]) & (t <= gt_t[-1])
        t, est, index = t[keep], est[keep], index[keep]
        nearest = gt_r[index]
        exact = slerp(t)
        world = procrustes([exact[i].as_matrix() @ est[i].as_matrix().T for i in range(len(t))])
        a, x = hand_eye(exact, est)
        residual = (exact.inv() * a.inv() * est * x.inv()).magnitude()
        # Angular speed (rad/s) of the ground truth between a frame and the one before.
        speed = np.r_[0.0, (exact[:-1].inv() * exact[1:]).magnitude() / np.diff(t)]
        print(f"{path} ({len(t)} frames associated)")
        print(f"  origin-aligned, nearest ground truth (the metric)  {origin_aligned(nearest, est):.3f}")
        print(f"  origin-aligned, interpolated ground truth          {origin_aligned(exact, est):.3f}")
        print(f"  best world rotation, interpolated                  {rms_deg(exact.inv() * world * est):.3f}")
        print(f"  hand-eye fit, interpolated (residual)              {rms_deg(exact.inv() * a.inv() * est * x.inv()):.3f}"
              f"   X = {np.round(x.as_rotvec() * 180.0 / np.pi, 2)} ({x.magnitude() * 180.0 / np.pi:.2f} deg)")
        print(f"  floor: perfect estimate, metric                    {origin_aligned(nearest, exact):.3f}")
        print(f"  floor: perfect estimate moving the fitted X frame  {origin_aligned(nearest, exact * x):.3f}")
        print(f"  correlation of the residual with angular speed     {np.corrcoef(residual, speed)[0, 1]:.2f}")


if __name__ == "__main__":
    main()
