"""Image files as other tools write them, for the dataset image reader's test
(trainer/tests/trainer/image_formats.rs): Pillow and OpenCV write each file, and NumPy writes
what a correct reader must return (RGB in [0, 1] as float64, masks as 0/1).

usage: image_fixtures.py DIR
"""
import sys
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

out = Path(sys.argv[1])
h, w = 12, 16
rng = np.random.default_rng(5)
yy, xx = np.mgrid[0:h, 0:w]

# 16-bit RGB PNG (OpenCV writes BGR order): precision beyond 8 bits must survive.
rgb16 = np.stack([xx * 4000 + 7, yy * 5000 + 3, (xx + yy) * 1500 + 1], axis=-1).astype(np.uint16)
cv2.imwrite(str(out / "rgb16.png"), rgb16[..., ::-1])
np.save(out / "rgb16_expected.npy", rgb16.astype(np.float64) / 65535.0)

# RGBA PNG: colour kept, alpha dropped.
rgba = rng.integers(0, 256, size=(h, w, 4), dtype=np.uint8)
Image.fromarray(rgba, "RGBA").save(out / "rgba.png")
np.save(out / "rgba_expected.npy", rgba[..., :3].astype(np.float64) / 255.0)

# Grey + alpha PNG: grey repeated in R, G, B.
la = rng.integers(0, 256, size=(h, w, 2), dtype=np.uint8)
Image.fromarray(la, "LA").save(out / "grey_alpha.png")
np.save(out / "grey_alpha_expected.npy", np.repeat(la[..., :1], 3, axis=-1).astype(np.float64) / 255.0)

# 16-bit grey mask: the person at 65535, a faint 200 (non-zero, far below half) elsewhere.
mask16 = np.full((h, w), 200, dtype=np.uint16)
mask16[3:9, 4:11] = 65535
Image.fromarray(mask16).save(out / "mask16.png")  # Pillow writes mode I;16 as 16-bit grey
np.save(out / "mask16_nonzero.npy", (mask16 > 0).astype(np.float64))
np.save(out / "mask16_half.npy", (mask16 >= 32768).astype(np.float64))

# RGB JPEG at quality 100 (what the reader returns is Pillow's decode of it, within
# rounding), and a CMYK JPEG of pure colours.
smooth = np.stack([xx * 15, yy * 20, 255 - xx * 15], axis=-1).astype(np.uint8)
Image.fromarray(smooth, "RGB").save(out / "rgb.jpg", quality=100)
np.save(out / "rgb_jpg_expected.npy", np.asarray(Image.open(out / "rgb.jpg").convert("RGB")).astype(np.float64) / 255.0)
cmyk = np.zeros((h, w, 4), dtype=np.uint8)
cmyk[:, : w // 2] = (0, 255, 255, 0)  # red
cmyk[:, w // 2 :] = (255, 0, 255, 0)  # green
Image.fromarray(cmyk, "CMYK").save(out / "cmyk.jpg", quality=100)
np.save(out / "cmyk_expected.npy", np.asarray(Image.open(out / "cmyk.jpg").convert("RGB")).astype(np.float64) / 255.0)

# A truncated JPEG.
data = (out / "rgb.jpg").read_bytes()
(out / "truncated.jpg").write_bytes(data[: len(data) // 2])
