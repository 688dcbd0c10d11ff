"""The scikit-image references of the evaluation metrics (trainer/tests/trainer/eval_metrics.rs).

Usage: skimage_metrics.py CASE_DIR. CASE_DIR holds case.json ({"pairs": [name, ...]})
and, for each name, NAME_a.npy and NAME_b.npy: H x W x 3 float64 images in [0, 1].
Writes, per name, NAME_ssim_map.npy (H x W x 3, skimage's full SSIM map) and
results.json ({name: {"psnr": dB, "ssim": mean}}).

PSNR: skimage.metrics.peak_signal_noise_ratio(a, b, data_range=1) (inf for identical
images is written as null). SSIM: structural_similarity with the 3DGS / Wang et al.
settings (Gaussian window, sigma 1.5, population covariance, data_range 1), channels
on the last axis; its filter pads by reflection and its mean is over the interior
(crop of (win_size - 1) / 2 = 5 pixels), which the Rust test accounts for.
"""
import json
import math
import sys
from pathlib import Path

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity


def main(case_dir: Path) -> None:
    case = json.loads((case_dir / "case.json").read_text())
    results = {}
    for name in case["pairs"]:
        a = np.load(case_dir / f"{name}_a.npy").astype(np.float64)
        b = np.load(case_dir / f"{name}_b.npy").astype(np.float64)
        assert a.shape == b.shape and a.ndim == 3 and a.shape[2] == 3, (name, a.shape, b.shape)
        psnr = peak_signal_noise_ratio(a, b, data_range=1)
        mean, full = structural_similarity(
            a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
            data_range=1, channel_axis=2, full=True,
        )
        np.save(case_dir / f"{name}_ssim_map.npy", np.ascontiguousarray(full, dtype=np.float64))
        results[name] = {"psnr": None if math.isinf(psnr) else float(psnr), "ssim": float(mean)}
    (case_dir / "results.json").write_text(json.dumps(results))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
