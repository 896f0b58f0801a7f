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
  angular speed (rolling shutter and timing errors grow with it);
- image latency: how far the image content lags its timestamp on the ground
  truth's clock, from the frame-to-frame rotations alone (they carry no drift
  and no origin): the shift of the ground truth that matches them best, over
  the whole clip and over each half;
- floors with that latency: a perfect estimate of what the images show (the
  ground truth that far back), scored like the metric, with X = identity and
  with the fitted X.
"""

import sys

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


# The metric's association: the ground-truth pose nearest in time, within 20 ms.
MAX_DIFF_S = 0.02

# Ground-truth shifts tried when measuring the image latency (seconds).
LATENCIES_S = np.arange(-0.03, 0.0301, 0.001)


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


def image_latency(gt_t, slerp, t, est, x):
    """The shift of the ground truth (seconds; positive: the images show an
    earlier pose than their timestamps say) whose frame-to-frame rotations, seen
    in the fitted camera frame X, best match the estimate's; and the RMS
    mismatch (degrees) at that shift and at no shift."""
    steps = (est[:-1].inv() * est[1:]).as_rotvec()

    def mismatch(latency):
        truth = slerp(np.clip(t - latency, gt_t[0], gt_t[-1])) * x
        truth_steps = (truth[:-1].inv() * truth[1:]).as_rotvec()
        return float(np.sqrt(np.mean(np.sum((steps - truth_steps) ** 2, axis=1))) * 180.0 / np.pi)

    errors = [mismatch(latency) for latency in LATENCIES_S]
    best = int(np.argmin(errors))
    return float(LATENCIES_S[best]), errors[best], mismatch(0.0)


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
        latency, best, unshifted = image_latency(gt_t, slerp, t, est, x)
        half = len(t) // 2
        first = image_latency(gt_t, slerp, t[:half], est[:half], x)[0]
        second = image_latency(gt_t, slerp, t[half:], est[half:], x)[0]
        print(f"  image latency from frame-to-frame rotations        {latency * 1e3:+.0f} ms"
              f" (step mismatch {unshifted:.3f} -> {best:.3f}; halves {first * 1e3:+.0f} / {second * 1e3:+.0f} ms)")
        seen = slerp(np.clip(t - latency, gt_t[0], gt_t[-1]))
        print(f"  floor: perfect estimate of the images, metric      {origin_aligned(nearest, seen):.3f}")
        print(f"  floor: the same moving the fitted X frame          {origin_aligned(nearest, seen * x):.3f}")


if __name__ == "__main__":
    main()
