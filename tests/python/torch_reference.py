"""PyTorch (CPU, float64) reference for drape's neural ops.

Usage: python torch_reference.py CASE_DIR

CASE_DIR holds case.json ({"op": ...}) and the op's inputs as float64 .npy files; the
outputs are written there as float64 .npy files. Ops:

  mlp       x, w{i}, b{i}, gy -> y, gx, gw{i}, gb{i}: nn.Linear layers with F.gelu (erf)
            or no activation, then heads over column ranges of the last layer
            (identity, sigmoid, exp, softmax(z / T)); gradients of sum(y * gy).
  triplane  planes (3, R, R, C) channels-last, points (n, 3), gfeat (n, 3C) -> feat,
            gplanes, gpoints: F.grid_sample(bilinear, zeros, align_corners=True) on
            the XY, XZ and YZ planes of the box-normalised points.
  rot6d     r6 (n, 6), gR (n, 3, 3) -> R, gr6: PyTorch3D's rotation_6d_to_matrix.
  ssim      img1, img2 (H, W, 3) -> ssim (1,), gimg1: pytorch_msssim.ssim, window 11,
            sigma 1.5, data range 1.
  l1        a, b -> loss (1,), ga: F.l1_loss.
"""

import json
import os
import sys

import numpy as np
import torch
import torch.nn.functional as F

torch.set_default_dtype(torch.float64)


def load(d, name):
    return torch.from_numpy(np.load(os.path.join(d, name + ".npy")).astype(np.float64))


def save(d, name, t):
    np.save(os.path.join(d, name + ".npy"), t.detach().cpu().numpy().astype(np.float64))


def grad_or_zeros(t):
    return t.grad if t.grad is not None else torch.zeros_like(t)


def op_mlp(d, case):
    x = load(d, "x").requires_grad_(True)
    layers = []
    for i, spec in enumerate(case["layers"]):
        lin = torch.nn.Linear(spec["in"], spec["out"], dtype=torch.float64)
        with torch.no_grad():
            lin.weight.copy_(load(d, f"w{i}").reshape(spec["out"], spec["in"]))
            lin.bias.copy_(load(d, f"b{i}").reshape(spec["out"]))
        layers.append((lin, spec["act"]))
    h = x
    for lin, act in layers:
        h = lin(h)
        if act == "gelu":
            h = F.gelu(h)
        elif act != "none":
            raise ValueError(f"unknown layer activation {act}")
    parts = []
    for head in case["heads"]:
        z = h[:, head["start"]:head["end"]]
        act = head["act"]
        if act == "identity":
            parts.append(z)
        elif act == "sigmoid":
            parts.append(torch.sigmoid(z))
        elif act == "exp":
            parts.append(torch.exp(z))
        elif act == "softmax":
            parts.append(torch.softmax(z / head["temperature"], dim=-1))
        else:
            raise ValueError(f"unknown head activation {act}")
    y = torch.cat(parts, dim=-1)
    gy = load(d, "gy").reshape(y.shape)
    (y * gy).sum().backward()
    save(d, "y", y)
    save(d, "gx", grad_or_zeros(x))
    for i, (lin, _) in enumerate(layers):
        save(d, f"gw{i}", grad_or_zeros(lin.weight))
        save(d, f"gb{i}", grad_or_zeros(lin.bias))


def op_triplane(d, case):
    planes = load(d, "planes").requires_grad_(True)  # (3, R, R, C)
    points = load(d, "points").requires_grad_(True)  # (n, 3)
    lo = torch.tensor(case["box_min"], dtype=torch.float64)
    hi = torch.tensor(case["box_max"], dtype=torch.float64)
    u = (points - lo) / (hi - lo) * 2.0 - 1.0
    axes = [(0, 1), (0, 2), (1, 2)]
    feats = []
    for p, (ax, ay) in enumerate(axes):
        plane = planes[p].permute(2, 0, 1).unsqueeze(0)  # (1, C, R, R): rows are y
        grid = torch.stack([u[:, ax], u[:, ay]], dim=-1).reshape(1, 1, -1, 2)
        f = F.grid_sample(plane, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        feats.append(f[0, :, 0, :].transpose(0, 1))  # (n, C)
    feat = torch.cat(feats, dim=-1)
    gfeat = load(d, "gfeat").reshape(feat.shape)
    (feat * gfeat).sum().backward()
    save(d, "feat", feat)
    save(d, "gplanes", grad_or_zeros(planes))
    save(d, "gpoints", grad_or_zeros(points))


def rotation_6d_to_matrix(r6):
    a1, a2 = r6[..., :3], r6[..., 3:]
    b1 = F.normalize(a1, dim=-1)
    b2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = F.normalize(b2, dim=-1)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-2)


def op_rot6d(d, case):
    r6 = load(d, "r6").requires_grad_(True)
    r = rotation_6d_to_matrix(r6)
    (r * load(d, "gR").reshape(r.shape)).sum().backward()
    save(d, "R", r)
    save(d, "gr6", grad_or_zeros(r6))


def op_ssim(d, case):
    from pytorch_msssim import ssim

    a = load(d, "img1").permute(2, 0, 1).unsqueeze(0).requires_grad_(True)
    b = load(d, "img2").permute(2, 0, 1).unsqueeze(0)
    s = ssim(a, b, data_range=1.0, size_average=True, win_size=11, win_sigma=1.5, K=(0.01, 0.03))
    s.backward()
    save(d, "ssim", s.reshape(1))
    save(d, "gimg1", grad_or_zeros(a)[0].permute(1, 2, 0))


def op_l1(d, case):
    a = load(d, "a").requires_grad_(True)
    loss = F.l1_loss(a, load(d, "b"))
    loss.backward()
    save(d, "loss", loss.reshape(1))
    save(d, "ga", grad_or_zeros(a))


OPS = {"mlp": op_mlp, "triplane": op_triplane, "rot6d": op_rot6d, "ssim": op_ssim, "l1": op_l1}


def main():
    if len(sys.argv) != 2:
        print("usage: torch_reference.py CASE_DIR", file=sys.stderr)
        return 2
    d = sys.argv[1]
    try:
        with open(os.path.join(d, "case.json")) as f:
            case = json.load(f)
        op = case["op"]
        if op not in OPS:
            raise ValueError(f"unknown op '{op}'")
        OPS[op](d, case)
    except Exception as e:  # one line, naming the case
        print(f"torch_reference: {d}: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
