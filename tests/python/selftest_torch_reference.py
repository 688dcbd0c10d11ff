"""Self-test of torch_reference.py against independent NumPy code.

Usage: PY tests/python/selftest_torch_reference.py   (PY from scripts/torch-env.sh)

Each op: random inputs, the script run as the tests run it, its outputs compared with
a NumPy forward pass, and its gradients with central finite differences of that NumPy
forward (so PyTorch's autograd is checked against an implementation that shares no code
with it). Also: n = 0 cases, and the one-line error on a bad case.
"""

import json
import math
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np

SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "torch_reference.py")
rng = np.random.default_rng(7)
results = {"passed": 0, "failed": 0}


def check(name, ok, detail=""):
    results["passed" if ok else "failed"] += 1
    print(f"{'ok  ' if ok else 'FAIL'} {name} {detail}")


def close(name, got, want, tol):
    got, want = np.asarray(got), np.asarray(want)
    if got.shape != want.shape:
        check(name, False, f"shape {got.shape} vs {want.shape}")
        return
    err = float(np.max(np.abs(got - want) / np.maximum(np.abs(want), 1.0))) if got.size else 0.0
    check(name, err <= tol, f"max err {err:.1e} (tol {tol:.0e})")


def run(case, arrays):
    d = tempfile.mkdtemp(prefix="torchref-")
    with open(os.path.join(d, "case.json"), "w") as f:
        json.dump(case, f)
    for k, v in arrays.items():
        np.save(os.path.join(d, k + ".npy"), np.ascontiguousarray(v, dtype=np.float64))
    p = subprocess.run([sys.executable, SCRIPT, d], capture_output=True, text=True)
    out = {}
    for name in os.listdir(d):
        if name.endswith(".npy") and name[:-4] not in arrays:
            a = np.load(os.path.join(d, name))
            assert a.dtype == np.float64 and a.flags.c_contiguous, name
            out[name[:-4]] = a
    shutil.rmtree(d)
    return p, out


def fd(f, x, eps=1e-6):
    """Central differences of the scalar f() w.r.t. every entry of x (changed in place)."""
    g = np.zeros_like(x)
    flat, gf = x.reshape(-1), g.reshape(-1)
    for i in range(flat.size):
        v = flat[i]
        flat[i] = v + eps
        up = f()
        flat[i] = v - eps
        down = f()
        flat[i] = v
        gf[i] = (up - down) / (2 * eps)
    return g


# ---- mlp -------------------------------------------------------------------------
erf = np.vectorize(math.erf, otypes=[float])


def mlp_np(x, ws, bs, acts, heads):
    h = x
    for w, b, a in zip(ws, bs, acts):
        h = h @ w.T + b
        if a == "gelu":
            h = 0.5 * h * (1.0 + erf(h / math.sqrt(2.0)))
    y = h.copy()
    for hd in heads:
        s, e = hd["start"], hd["end"]
        z = h[:, s:e]
        if hd["act"] == "sigmoid":
            y[:, s:e] = 1.0 / (1.0 + np.exp(-z))
        elif hd["act"] == "exp":
            y[:, s:e] = np.exp(z)
        elif hd["act"] == "softmax":
            t = z / hd["temperature"]
            t = np.exp(t - t.max(axis=1, keepdims=True))
            y[:, s:e] = t / t.sum(axis=1, keepdims=True)
    return y


def test_mlp(n):
    dims, acts = [4, 6, 5, 9], ["gelu", "gelu", "none"]
    # Out of order on purpose; column 3 has no head (passes through).
    heads = [
        {"start": 4, "end": 8, "act": "softmax", "temperature": 0.5},
        {"start": 0, "end": 1, "act": "sigmoid"},
        {"start": 1, "end": 3, "act": "identity"},
        {"start": 8, "end": 9, "act": "exp"},
    ]
    x = rng.normal(size=(n, dims[0]))
    ws = [rng.normal(size=(dims[i + 1], dims[i])) * 0.7 for i in range(3)]
    bs = [rng.normal(size=dims[i + 1]) * 0.3 for i in range(3)]
    gy = rng.normal(size=(n, dims[-1]))
    arrays = {"x": x, "gy": gy}
    for i in range(3):
        arrays[f"w{i}"], arrays[f"b{i}"] = ws[i], bs[i]
    layers = [{"in": dims[i], "out": dims[i + 1], "act": acts[i]} for i in range(3)]
    p, out = run({"op": "mlp", "layers": layers, "heads": heads}, arrays)
    check(f"mlp n={n}: exit 0", p.returncode == 0, p.stderr.strip())
    if p.returncode:
        return
    close(f"mlp n={n}: y vs numpy", out["y"], mlp_np(x, ws, bs, acts, heads), 1e-12)
    loss = lambda: float(np.sum(mlp_np(x, ws, bs, acts, heads) * gy))
    close(f"mlp n={n}: gx vs finite differences", out["gx"], fd(loss, x), 1e-7)
    for i in range(3):
        close(f"mlp n={n}: gw{i} vs finite differences", out[f"gw{i}"], fd(loss, ws[i]), 1e-7)
        close(f"mlp n={n}: gb{i} vs finite differences", out[f"gb{i}"], fd(loss, bs[i]), 1e-7)


# ---- triplane ----------------------------------------------------------------------
def bilinear_np(plane, gx, gy):
    """plane (R, R, C) channels-last, rows = y; grid coordinates in [-1, 1] (align_corners)."""
    r = plane.shape[0]
    out = np.zeros((gx.size, plane.shape[2]))
    for k, (u, v) in enumerate(zip(gx, gy)):
        fx, fy = (u + 1) / 2 * (r - 1), (v + 1) / 2 * (r - 1)
        x0, y0 = math.floor(fx), math.floor(fy)
        for xi, wx in ((x0, 1 - (fx - x0)), (x0 + 1, fx - x0)):
            for yi, wy in ((y0, 1 - (fy - y0)), (y0 + 1, fy - y0)):
                if 0 <= xi < r and 0 <= yi < r:
                    out[k] += wx * wy * plane[yi, xi]
    return out


def triplane_np(planes, pts, lo, hi):
    u = (pts - lo) / (hi - lo) * 2 - 1
    return np.concatenate([bilinear_np(planes[p], u[:, a], u[:, b]) for p, (a, b) in enumerate([(0, 1), (0, 2), (1, 2)])], axis=1)


def test_triplane():
    r, c, n = 5, 2, 24
    lo, hi = np.array([-1.0, -0.3, -2.0]), np.array([0.8, 1.7, 0.5])
    planes = rng.normal(size=(3, r, r, c))
    # Inside and up to 10% outside the box, but off the texel lines (finite differences
    # across a line of the bilinear interpolant would be meaningless).
    t = rng.uniform(-0.1, 1.1, size=(n, 3))
    cell = t * (r - 1)
    t = np.where(np.abs(cell - np.round(cell)) < 0.05, t + 0.1 / (r - 1), t)
    pts = lo + t * (hi - lo)
    gfeat = rng.normal(size=(n, 3 * c))
    case = {"op": "triplane", "box_min": lo.tolist(), "box_max": hi.tolist()}
    p, out = run(case, {"planes": planes, "points": pts, "gfeat": gfeat})
    check("triplane: exit 0", p.returncode == 0, p.stderr.strip())
    if p.returncode:
        return
    close("triplane: feat vs numpy bilinear", out["feat"], triplane_np(planes, pts, lo, hi), 1e-12)
    loss = lambda: float(np.sum(triplane_np(planes, pts, lo, hi) * gfeat))
    close("triplane: gplanes vs finite differences", out["gplanes"], fd(loss, planes), 1e-7)
    close("triplane: gpoints vs finite differences", out["gpoints"], fd(loss, pts), 1e-6)
    # Exactly on the box's corners and faces: the forward values are the corner texels.
    corners = np.array([lo, hi, [lo[0], hi[1], lo[2]]])
    p, out = run(case, {"planes": planes, "points": corners, "gfeat": np.ones((3, 3 * c))})
    close("triplane: box corners hit corner texels", out["feat"], triplane_np(planes, corners, lo, hi), 1e-12)
    check("triplane: box_min corner = texel [0][0]", np.allclose(out["feat"][0, :c], planes[0, 0, 0]))
    check("triplane: box_max corner = texel [R-1][R-1]", np.allclose(out["feat"][1, :c], planes[0, r - 1, r - 1]))
    check("triplane: (x=min, y=max) = texel row R-1, col 0", np.allclose(out["feat"][2, :c], planes[0, r - 1, 0]))
    # n = 0.
    p, out = run(case, {"planes": planes, "points": np.zeros((0, 3)), "gfeat": np.zeros((0, 3 * c))})
    ok = p.returncode == 0 and out["feat"].shape == (0, 3 * c) and out["gpoints"].shape == (0, 3) and not out["gplanes"].any()
    check("triplane n=0: empty outputs, zero plane gradient", ok, p.stderr.strip())


# ---- rot6d -------------------------------------------------------------------------
def rot6d_np(r6):
    a1, a2 = r6[:, :3], r6[:, 3:]
    b1 = a1 / np.linalg.norm(a1, axis=1, keepdims=True)
    b2 = a2 - np.sum(b1 * a2, axis=1, keepdims=True) * b1
    b2 /= np.linalg.norm(b2, axis=1, keepdims=True)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=1)


def test_rot6d():
    n = 20
    r6, g = rng.normal(size=(n, 6)) * 2, rng.normal(size=(n, 3, 3))
    p, out = run({"op": "rot6d"}, {"r6": r6, "gR": g})
    check("rot6d: exit 0", p.returncode == 0, p.stderr.strip())
    if p.returncode:
        return
    R = out["R"]
    close("rot6d: R R^T = I", np.einsum("nij,nkj->nik", R, R), np.broadcast_to(np.eye(3), (n, 3, 3)), 1e-13)
    close("rot6d: det R = +1", np.linalg.det(R), np.ones(n), 1e-13)
    close("rot6d: row 0 = a1 / |a1|", R[:, 0], r6[:, :3] / np.linalg.norm(r6[:, :3], axis=1, keepdims=True), 1e-14)
    close("rot6d: R vs numpy", R, rot6d_np(r6), 1e-13)
    close("rot6d: gr6 vs finite differences", out["gr6"], fd(lambda: float(np.sum(rot6d_np(r6) * g)), r6), 1e-7)


# ---- ssim --------------------------------------------------------------------------
def ssim_np(a, b):
    """Mean SSIM with an 11-tap sigma 1.5 Gaussian, 'valid' (no padding), per channel."""
    k = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    k /= k.sum()

    def blur(im):  # (H, W, 3) -> (H-10, W-10, 3)
        h = sum(k[i] * im[i : im.shape[0] - 10 + i] for i in range(11))
        return sum(k[i] * h[:, i : im.shape[1] - 10 + i] for i in range(11))

    c1, c2 = 0.01**2, 0.03**2
    m1, m2 = blur(a), blur(b)
    s11, s22, s12 = blur(a * a) - m1 * m1, blur(b * b) - m2 * m2, blur(a * b) - m1 * m2
    m = (2 * m1 * m2 + c1) / (m1 * m1 + m2 * m2 + c1) * (2 * s12 + c2) / (s11 + s22 + c2)
    return float(m.mean())


def test_ssim():
    h, w = 16, 13
    b = np.clip(0.5 + 0.3 * np.sin(np.arange(h * w * 3).reshape(h, w, 3) * 0.05) + rng.uniform(-0.1, 0.1, (h, w, 3)), 0, 1)
    a = np.clip(b + rng.uniform(-0.2, 0.2, (h, w, 3)), 0, 1)
    p, out = run({"op": "ssim"}, {"img1": a, "img2": b})
    check("ssim: exit 0", p.returncode == 0, p.stderr.strip())
    if p.returncode:
        return
    check("ssim: shape (1,)", out["ssim"].shape == (1,))
    close("ssim: value vs numpy (float64 window, valid)", out["ssim"][0], ssim_np(a, b), 1e-14)
    close("ssim: gimg1 vs finite differences", out["gimg1"], fd(lambda: ssim_np(a, b), a), 1e-8)
    p, _ = run({"op": "ssim"}, {"img1": a[:10], "img2": b[:10]})
    check("ssim: smaller than the window is refused", p.returncode == 1 and "window" in p.stderr, p.stderr.strip())


# ---- l1 ----------------------------------------------------------------------------
def test_l1():
    a, b = rng.normal(size=(7, 5, 3)), rng.normal(size=(7, 5, 3))
    p, out = run({"op": "l1"}, {"a": a, "b": b})
    check("l1: exit 0", p.returncode == 0, p.stderr.strip())
    if p.returncode:
        return
    close("l1: loss = mean |a - b|", out["loss"], [np.mean(np.abs(a - b))], 1e-15)
    close("l1: ga = sign(a - b) / N", out["ga"], np.sign(a - b) / a.size, 1e-15)


# ---- errors ------------------------------------------------------------------------
def test_errors():
    p, _ = run({"op": "rot6d"}, {"r6": np.zeros((2, 6))})
    lines = p.stderr.strip().splitlines()
    check("error: missing file -> exit 1, one line naming op and file", p.returncode == 1 and len(lines) == 1 and "rot6d" in lines[0] and "gR.npy" in lines[0], p.stderr.strip())
    p, _ = run({"op": "rot6d"}, {"r6": np.zeros((2, 6)), "gR": np.zeros((2, 9))})
    check("error: wrong shape -> exit 1 naming the file", p.returncode == 1 and "gR.npy" in p.stderr, p.stderr.strip())
    p, _ = run({"op": "conv"}, {})
    check("error: unknown op -> exit 1", p.returncode == 1 and "conv" in p.stderr, p.stderr.strip())
    layers = [{"in": 3, "out": 2, "act": "none"}]
    p, _ = run({"op": "mlp", "layers": layers, "heads": []}, {"x": np.zeros((1, 3)), "w0": np.zeros((3, 2)), "b0": np.zeros(2), "gy": np.zeros((1, 2))})
    check("error: transposed weight -> exit 1 naming w0.npy", p.returncode == 1 and "w0.npy" in p.stderr, p.stderr.strip())


if __name__ == "__main__":
    test_mlp(3)
    test_mlp(0)
    test_triplane()
    test_rot6d()
    test_ssim()
    test_l1()
    test_errors()
    print(f"{results['passed']} passed, {results['failed']} failed")
    sys.exit(1 if results["failed"] else 0)
