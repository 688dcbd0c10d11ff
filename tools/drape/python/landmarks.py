"""Run mediapipe's legacy Pose on one view's frames: 33 body landmarks and a person mask.

`drape prepare` decodes, calibrates, fits and writes the dataset in Rust; this script
only runs the model (there is no Rust port of it) and writes plain files:

  python landmarks.py FRAMES_DIR OUT_DIR [--roi ROI.npy]

FRAMES_DIR holds one view's frames as PNG (000000.png, ...), processed in name order
as ONE video: static_image_mode=False, so the model tracks the person from frame to
frame (one invocation per view; never mix views in one run). OUT_DIR receives:

  masks/<frame name>.png  8-bit grey person mask, round(255 * p) of mediapipe's float
                          segmentation p in [0, 1], at the frame's full size. The soft
                          edge is kept; >= 128 is mediapipe's usual p >= 0.5 cut.
                          All zero where nothing was detected.
  landmarks.npy           float32 [frames, 33, 5]: x_px, y_px, z, visibility, presence
                          (legacy Pose never sets presence: that column is NaN).
                          x_px = x * width, y_px = y * height in the full frame's pixels
                          (mediapipe's normalised coordinates, 0 = the image's left/top
                          edge). z is mediapipe's relative depth (origin at the hips'
                          midpoint, smaller = nearer the camera) scaled like x to pixels
                          (z * width).
  world_landmarks.npy     float32 [frames, 33, 3]: mediapipe's metric 3D pose in metres,
                          origin at the hips' midpoint, in the camera's orientation.
  detected.npy            bool [frames]. Rows of frames where nothing was detected are NaN.
  frames.txt              the frame file names, one a line, in the arrays' order.

--roi ROI.npy: float [frames, 4] boxes x0, y0, x1, y1 in pixels (a NaN row: whole
frame). Legacy Pose follows ONE person (whichever its detector picked first, then by
tracking; it may slide onto another person who passes in front), so this is how the
caller makes it follow a chosen one: everything outside the box is painted black and
the frame keeps its size, so coordinates and the tracker's state stay those of the full
frame while the box moves. (Cropping to the box instead fails: mediapipe's segmentation
smoothing rejects frames whose size changes.) On pose2sim's Demo_MultiPerson, boxes
projected from another two views' triangulation kept cam01 and cam02 on the chosen
person in 100/100 frames, where without them both followed the other one.

Deterministic (CPU, XNNPACK, no randomness) and offline: the model files are inside the
mediapipe 0.10.21 wheel (model_complexity=1; 0 and 2 would download theirs).
Progress goes to stderr.
"""
import argparse
import os
import sys
import time

import cv2
import numpy as np

N = 33


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("frames_dir")
    ap.add_argument("out_dir")
    ap.add_argument("--roi", help="float [frames, 4] .npy of x0, y0, x1, y1 boxes (NaN row: whole frame)")
    args = ap.parse_args()

    names = sorted(n for n in os.listdir(args.frames_dir) if n.lower().endswith(".png"))
    if not names:
        sys.exit(f"error: no .png frames in {args.frames_dir}")
    rois = None
    if args.roi:
        rois = np.load(args.roi).astype(np.float64)
        if rois.shape != (len(names), 4):
            sys.exit(f"error: {args.roi} has shape {rois.shape}, want ({len(names)}, 4)")
    os.makedirs(os.path.join(args.out_dir, "masks"), exist_ok=True)

    # Imported here so that --help and argument errors need no mediapipe.
    import mediapipe as mp

    lms = np.full((len(names), N, 5), np.nan, np.float32)
    world = np.full((len(names), N, 3), np.nan, np.float32)
    detected = np.zeros(len(names), bool)
    pose = mp.solutions.pose.Pose(static_image_mode=False, model_complexity=1,
                                  enable_segmentation=True, smooth_landmarks=True,
                                  smooth_segmentation=True)
    start, model_s = time.perf_counter(), 0.0
    for i, name in enumerate(names):
        bgr = cv2.imread(os.path.join(args.frames_dir, name), cv2.IMREAD_COLOR)
        if bgr is None:
            sys.exit(f"error: cannot read {name}")
        h, w = bgr.shape[:2]
        x0, y0, x1, y1 = 0, 0, w, h
        if rois is not None and not np.isnan(rois[i]).any():
            # Whole pixels, clamped to the frame; an empty box is the whole frame.
            bx0, by0 = (max(0, int(np.floor(v))) for v in rois[i, :2])
            bx1, by1 = min(w, int(np.ceil(rois[i, 2]))), min(h, int(np.ceil(rois[i, 3])))
            if bx1 > bx0 and by1 > by0:
                x0, y0, x1, y1 = bx0, by0, bx1, by1
        image = bgr
        if (x0, y0, x1, y1) != (0, 0, w, h):
            image = np.zeros_like(bgr)
            image[y0:y1, x0:x1] = bgr[y0:y1, x0:x1]
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        t = time.perf_counter()
        result = pose.process(rgb)
        model_s += time.perf_counter() - t

        mask = np.zeros((h, w), np.uint8)
        if result.pose_landmarks is not None:
            detected[i] = True
            # Legacy Pose fills visibility but never presence: NaN when unset.
            lms[i] = [[l.x * w, l.y * h, l.z * w, l.visibility,
                       l.presence if l.HasField("presence") else np.nan]
                      for l in result.pose_landmarks.landmark]
            world[i] = [[l.x, l.y, l.z] for l in result.pose_world_landmarks.landmark]
            if result.segmentation_mask is not None:
                m = np.clip(result.segmentation_mask, 0.0, 1.0)
                mask = np.rint(m * 255.0).astype(np.uint8)
        cv2.imwrite(os.path.join(args.out_dir, "masks", os.path.splitext(name)[0] + ".png"), mask)

        ms, model_ms = (1000.0 * v / (i + 1) for v in (time.perf_counter() - start, model_s))
        print(f"landmarks: {i + 1}/{len(names)} frames, {ms:.1f} ms/frame ({model_ms:.1f} in the model)",
              file=sys.stderr, flush=True)
    pose.close()

    np.save(os.path.join(args.out_dir, "landmarks.npy"), lms)
    np.save(os.path.join(args.out_dir, "world_landmarks.npy"), world)
    np.save(os.path.join(args.out_dir, "detected.npy"), detected)
    with open(os.path.join(args.out_dir, "frames.txt"), "w") as f:
        f.write("".join(n + "\n" for n in names))
    print(f"landmarks: detected in {int(detected.sum())}/{len(names)} frames", file=sys.stderr)


if __name__ == "__main__":
    main()
