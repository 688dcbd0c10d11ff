"""The OpenCV references of lens distortion (trainer/tests/trainer/distortion.rs).

Usage: opencv_reference.py CASE_DIR... Each CASE_DIR holds case.json with "kind",
"K" (3 x 3, rows) and "D" (k1 k2 p1 p2 k3), and:

- kind "project": "R" (3 x 3 world-to-camera rows), "t" (3) and points.npy (N x 3,
  world). Writes projected.npy (N x 2): cv2.projectPoints(points, Rodrigues(R), t, K, D);
  and undistorted.npy (N x 2): cv2.undistortPointsIter of those pixels back to
  normalized coordinates with a tight criterion (the default, 5 fixed-point steps, is
  too coarse to compare against an inverse converged to 1e-14).
- kind "image": image.npy (H x W x 3, 8-bit values as float64) and mask.npy (H x W, 0
  or 1). Writes map_x.npy, map_y.npy (H x W): cv2.initUndistortRectifyMap(K, D, None,
  K, (W, H), CV_32FC1); undistorted.npy: cv2.undistort(image as uint8, K, D);
  mask_undistorted.npy: cv2.undistort(mask * 255 as uint8, K, D), values 0..255.

K is passed as OpenCV reads it (pixel centres at integers); the Rust test shifts
drape's principal point by -0.5 before writing it.
"""
import json
import sys
from pathlib import Path

import cv2
import numpy as np


def project(case_dir: Path, case: dict, K: np.ndarray, D: np.ndarray) -> None:
    R = np.array(case["R"], dtype=np.float64)
    t = np.array(case["t"], dtype=np.float64).reshape(3, 1)
    points = np.load(case_dir / "points.npy").astype(np.float64).reshape(-1, 1, 3)
    rvec, _ = cv2.Rodrigues(R)
    projected, _ = cv2.projectPoints(points, rvec, t, K, D)
    projected = projected.reshape(-1, 2)
    np.save(case_dir / "projected.npy", np.ascontiguousarray(projected, dtype=np.float64))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    undistorted = cv2.undistortPointsIter(projected.reshape(-1, 1, 2), K, D, None, None, criteria)
    np.save(case_dir / "undistorted.npy", np.ascontiguousarray(undistorted.reshape(-1, 2), dtype=np.float64))


def image(case_dir: Path, K: np.ndarray, D: np.ndarray) -> None:
    img = np.load(case_dir / "image.npy")
    assert img.ndim == 3 and img.shape[2] == 3, img.shape
    assert np.all(img == np.round(img)) and img.min() >= 0 and img.max() <= 255
    h, w = img.shape[:2]
    map_x, map_y = cv2.initUndistortRectifyMap(K, D, None, K, (w, h), cv2.CV_32FC1)
    np.save(case_dir / "map_x.npy", map_x.astype(np.float64))
    np.save(case_dir / "map_y.npy", map_y.astype(np.float64))
    out = cv2.undistort(np.ascontiguousarray(img.astype(np.uint8)), K, D)
    np.save(case_dir / "undistorted.npy", out.astype(np.float64))
    mask = np.load(case_dir / "mask.npy")
    assert mask.shape == (h, w) and set(np.unique(mask)) <= {0.0, 1.0}
    out = cv2.undistort(np.ascontiguousarray((mask * 255).astype(np.uint8)), K, D)
    np.save(case_dir / "mask_undistorted.npy", out.astype(np.float64))


def main(case_dirs: list) -> None:
    for case_dir in map(Path, case_dirs):
        case = json.loads((case_dir / "case.json").read_text())
        K = np.array(case["K"], dtype=np.float64)
        D = np.array(case["D"], dtype=np.float64)
        assert K.shape == (3, 3) and D.shape == (5,), (K.shape, D.shape)
        if case["kind"] == "project":
            project(case_dir, case, K, D)
        elif case["kind"] == "image":
            image(case_dir, K, D)
        else:
            raise ValueError(f"{case_dir}: unknown kind {case['kind']!r}")


if __name__ == "__main__":
    main(sys.argv[1:])
