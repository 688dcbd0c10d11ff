"""The held-out baseline of docs/results.md: every held-out image's person mask filled
with the person's mean colour over the training images, black elsewhere (drape's
evaluation compares against the person on black), scored as drape eval scores a render:
PSNR in the person mask's bounding box, the mean over the held-out images.

Usage: python3 scripts/mean-colour-baseline.py SEQUENCE --train cam01,cam02,cam03 --test cam04

SEQUENCE is a zju-refined sequence (drape prepare's DIR/sequence): images/<camera>/,
mask/<camera>/ (any non-zero pixel is the person). numpy and Pillow only. The masks are
read as written (drape's loader also undoes the lens distortion on them; for Pose2Sim's
cameras that moves an edge by well under a pixel at 256 px).
"""

import argparse
import glob
import os

import numpy as np
from PIL import Image


def pairs(seq, camera):
    for path in sorted(glob.glob(os.path.join(seq, "images", camera, "*.png"))):
        mask = os.path.join(seq, "mask", camera, os.path.basename(path))
        rgb = np.asarray(Image.open(path).convert("RGB"), np.float64) / 255.0
        m = np.asarray(Image.open(mask).convert("L")) > 0
        yield rgb, m


def psnr(a, b):
    mse = np.mean((a - b) ** 2)
    return -10.0 * np.log10(max(mse, 1e-20))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("--train", required=True, help="training cameras, comma-separated names")
    ap.add_argument("--test", required=True, help="held-out cameras, comma-separated names")
    args = ap.parse_args()
    total, count = np.zeros(3), 0
    for cam in args.train.split(","):
        for rgb, m in pairs(args.sequence, cam):
            total += rgb[m].sum(axis=0)
            count += int(m.sum())
    if count == 0:
        raise SystemExit("no person pixel in the training masks")
    mean = total / count
    scores = []
    for cam in args.test.split(","):
        for rgb, m in pairs(args.sequence, cam):
            if not m.any():
                continue
            ys, xs = np.nonzero(m)
            box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
            truth = rgb * m[..., None]
            base = mean[None, None, :] * m[..., None]
            scores.append(psnr(base[box], truth[box]))
    print(f"mean training colour (RGB 0-1): {np.round(mean, 4).tolist()}")
    print(f"held-out images: {len(scores)}")
    print(f"baseline PSNR in the person's box: {np.mean(scores):.2f} dB")


if __name__ == "__main__":
    main()
