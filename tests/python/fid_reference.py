"""The FID references (trainer/tests/trainer/fid.rs): pytorch-fid's network and Fréchet distance.

Usage: fid_reference.py CASE_DIR. CASE_DIR holds case.json; exit status 0, or 1 with one
line on stderr. Cases:

  network   {"converter": path of scripts/fid-to-safetensors.py, "seed": S,
            "images": [NAME, ...]}, NAME.npy (H x W x 3 in [0, 1]) -> weights.safetensors
            (the converter's `state()` of its seeded random FID Inception) and, per
            image, NAME_features.npy (2048,): the converter's `pool3` (pytorch-fid's
            InceptionV3 forward: resize to 299, [-1, 1], blocks, average pool) in float64,
            and NAME_features_f32.npy, the same network in float32 (how far PyTorch's
            own f32 lands from its f64).
  frechet   {"seed": S, "dim": D, "sets": {NAME: [n1, n2], ...}} -> mu1, mu2 (D,), sigma1,
            sigma2 (D, D): random SPD covariances and means; and per set NAME_f1 (n1, D),
            NAME_f2 (n2, D): random features, rounded to float32 (n2 = 0: the second
            set is the first).
            results.json: {"stats": FID of (mu1, sigma1, mu2, sigma2), NAME: FID of the
            sets' np.mean / np.cov, ...}, each by pytorch-fid's
            calculate_frechet_distance (copied below: scipy.linalg.sqrtm of sigma1 @ sigma2,
            the eps retry, the imaginary check), plus "NAME_svd": the same distance with
            the trace term as the nuclear norm of A1 A2^T (numpy SVD), exact also when
            n < D where sqrtm of the singular product is not.
"""
import importlib.util
import json
import os
import sys

import numpy as np
from scipy import linalg


def calculate_frechet_distance(mu1, sigma1, mu2, sigma2, eps=1e-6):
    """pytorch_fid.fid_score.calculate_frechet_distance (0.3.0), unchanged but for the
    message printed to stderr."""
    mu1 = np.atleast_1d(mu1)
    mu2 = np.atleast_1d(mu2)
    sigma1 = np.atleast_2d(sigma1)
    sigma2 = np.atleast_2d(sigma2)
    assert mu1.shape == mu2.shape, "Training and test mean vectors have different lengths"
    assert sigma1.shape == sigma2.shape, "Training and test covariances have different dimensions"
    diff = mu1 - mu2
    covmean, _ = linalg.sqrtm(sigma1.dot(sigma2), disp=False)
    if not np.isfinite(covmean).all():
        print(f"fid calculation produces singular product; adding {eps} to diagonal of cov estimates", file=sys.stderr)
        offset = np.eye(sigma1.shape[0]) * eps
        covmean = linalg.sqrtm((sigma1 + offset).dot(sigma2 + offset))
    if np.iscomplexobj(covmean):
        if not np.allclose(np.diagonal(covmean).imag, 0, atol=1e-3):
            m = np.max(np.abs(covmean.imag))
            raise ValueError("Imaginary component {}".format(m))
        covmean = covmean.real
    tr_covmean = np.trace(covmean)
    return diff.dot(diff) + np.trace(sigma1) + np.trace(sigma2) - 2 * tr_covmean


def frechet_svd(f1, f2):
    a1 = (f1 - f1.mean(0)) / np.sqrt(len(f1) - 1)
    a2 = (f2 - f2.mean(0)) / np.sqrt(len(f2) - 1)
    diff = f1.mean(0) - f2.mean(0)
    nuclear = np.linalg.svd(a1 @ a2.T, compute_uv=False).sum()
    return diff.dot(diff) + (a1 * a1).sum() + (a2 * a2).sum() - 2 * nuclear


def case_network(d, case):
    import torch
    from safetensors.torch import save_file

    spec = importlib.util.spec_from_file_location("fid_convert", case["converter"])
    conv = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conv)
    model = conv.build(random_seed=int(case["seed"]))
    save_file(conv.state(model), os.path.join(d, "weights.safetensors"))
    torch.set_num_threads(2)
    with torch.no_grad():
        for name in case["images"]:
            img = np.load(os.path.join(d, name + ".npy"))
            assert img.ndim == 3 and img.shape[2] == 3, (name, img.shape)
            x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).unsqueeze(0)
            f64 = conv.pool3(model.double(), x.double())[0]
            f32 = conv.pool3(model.float(), x.float())[0]
            np.save(os.path.join(d, name + "_features.npy"), f64.numpy().astype(np.float64))
            np.save(os.path.join(d, name + "_features_f32.npy"), f32.numpy().astype(np.float64))


def case_frechet(d, case):
    rng = np.random.default_rng(int(case["seed"]))
    dim = int(case["dim"])

    def spd():
        a = rng.standard_normal((dim, dim))
        return a @ a.T / dim + 0.05 * np.eye(dim)

    mu1, mu2 = rng.standard_normal(dim), 0.5 * rng.standard_normal(dim)
    s1, s2 = spd(), spd()
    for name, v in [("mu1", mu1), ("mu2", mu2), ("sigma1", s1), ("sigma2", s2)]:
        np.save(os.path.join(d, name + ".npy"), v)
    results = {"stats": float(calculate_frechet_distance(mu1, s1, mu2, s2))}
    for name, (n1, n2) in case["sets"].items():
        # Features of a few hundred-ish scale with correlated dimensions, as pool3's.
        mix = rng.standard_normal((dim, dim)) / np.sqrt(dim)
        f1 = rng.standard_normal((n1, dim)) @ mix + 0.3
        f2 = f1 if n2 == 0 else rng.standard_normal((n2, dim)) @ mix * 1.2 + 0.25
        # Rounded to float32, as drape holds features, so both sides see the same numbers.
        f1, f2 = (f.astype(np.float32).astype(np.float64) for f in (f1, f2))
        np.save(os.path.join(d, name + "_f1.npy"), f1)
        np.save(os.path.join(d, name + "_f2.npy"), f2)
        stats = [(f.mean(0), np.cov(f, rowvar=False)) for f in (f1, f2)]
        results[name] = float(calculate_frechet_distance(stats[0][0], stats[0][1], stats[1][0], stats[1][1]))
        results[name + "_svd"] = float(frechet_svd(f1, f2))
    with open(os.path.join(d, "results.json"), "w") as f:
        json.dump(results, f)


CASES = {"network": case_network, "frechet": case_frechet}


def main():
    if len(sys.argv) != 2:
        print("usage: fid_reference.py CASE_DIR", file=sys.stderr)
        return 1
    d = sys.argv[1]
    kind = "?"
    try:
        with open(os.path.join(d, "case.json")) as f:
            case = json.load(f)
        kind = str(case.get("case", "?"))
        if kind not in CASES:
            raise ValueError(f"unknown case '{kind}' (known: {', '.join(CASES)})")
        CASES[kind](d, case)
    except Exception as e:  # one line, naming the case
        msg = f"fid_reference: {kind}: {d}: {type(e).__name__}: {e}"
        print(" ".join(msg.split()), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
