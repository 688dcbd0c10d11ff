"""PyTorch (CPU, float64) reference for drape's neural ops.

Usage: python torch_reference.py CASE_DIR

CASE_DIR holds case.json ({"op": ...}) and the op's inputs as float64 .npy files (C
order); the outputs are written there as float64, C-order .npy files. Exit status 0, or
1 with one line on stderr naming the op and the file at fault. Ops:

  mlp       x (n, in0), w{i} (out, in), b{i} (out,), gy (n, out_last)
            -> y, gx, gw{i}, gb{i}: nn.Linear layers (a layer with "weight_norm":
            true is wrapped in torch's weight_norm(dim=0) with v = w{i}, g = g{i}
            (out,), and also gives gg{i}; gw{i} is then v's gradient), each followed by F.gelu (erf
            form) or nothing, then heads over column ranges [start, end) of the last
            layer (identity, sigmoid, exp, softmax(z / T) over the range; columns no
            head covers pass through); gradients of sum(y * gy). n may be 0.
  triplane  planes (3, R, R, C) channels-last (planes[p][row = y][col = x][c]),
            points (n, 3), gfeat (n, 3C) -> feat (n, 3C), gplanes, gpoints:
            F.grid_sample(bilinear, zeros padding, align_corners=True) on the XY, XZ
            and YZ planes at u = (p - box_min) / (box_max - box_min) * 2 - 1;
            gradients of sum(feat * gfeat), gpoints through the box mapping.
  rot6d     r6 (n, 6), gR (n, 3, 3) -> R (rows b1, b2, b3), gr6: PyTorch3D's
            rotation_6d_to_matrix (Zhou et al. 2019), written out here.
  ssim      img1, img2 (H, W, 3) -> ssim (1,), gimg1: pytorch_msssim.ssim (valid
            11-tap Gaussian, sigma 1.5, data range 1, K = (0.01, 0.03)) with the
            window built in float64.
  l1        a, b (same shape) -> loss (1,), ga: F.l1_loss (mean |a - b|).
  pose_blend pose (24, 3) axis-angles, basis (n, 207, 3), decoded (n, 3), g (n, 3)
            -> features (207,): (R_j - I) of joints 1-23 by smplx's Rodrigues, offsets
            (n, 3) = decoded + einsum(basis, features), gbasis: gradient of
            sum(offsets * g).
"""

import json
import os
import sys

import torch
import torch.nn.functional as F

from case_io import CaseError, grad_or_zeros, load, save  # tests/python/case_io.py

torch.set_default_dtype(torch.float64)


def op_mlp(d, case):
    specs = case["layers"]
    if not specs:
        raise CaseError("case.json: 'layers' is empty")
    for i in range(1, len(specs)):
        if specs[i]["in"] != specs[i - 1]["out"]:
            raise CaseError(f"case.json: layer {i} takes {specs[i]['in']} inputs but layer {i - 1} gives {specs[i - 1]['out']}")
    x = load(d, "x", (None, specs[0]["in"])).requires_grad_(True)
    n = x.shape[0]
    layers = []
    for i, spec in enumerate(specs):
        if spec["act"] not in ("gelu", "none"):
            raise CaseError(f"case.json: layer {i}: unknown activation '{spec['act']}'")
        lin = torch.nn.Linear(spec["in"], spec["out"], dtype=torch.float64)
        with torch.no_grad():
            lin.weight.copy_(load(d, f"w{i}", (spec["out"], spec["in"])))
            lin.bias.copy_(load(d, f"b{i}", (spec["out"],)))
        if spec.get("weight_norm"):
            # PyTorch's own weight normalisation (dim=0): original0 is g (out, 1),
            # original1 is v; w{i} holds v and g{i} holds g.
            lin = torch.nn.utils.parametrizations.weight_norm(lin, dim=0)
            with torch.no_grad():
                lin.parametrizations.weight.original0.copy_(load(d, f"g{i}", (spec["out"],)).view(-1, 1))
                lin.parametrizations.weight.original1.copy_(load(d, f"w{i}", (spec["out"], spec["in"])))
        layers.append((lin, spec["act"]))
    h = x
    for lin, act in layers:
        h = lin(h)
        if act == "gelu":
            h = F.gelu(h)  # approximate="none": x * Phi(x) with erf
    width = h.shape[1]
    heads = sorted(case.get("heads", []), key=lambda hd: hd["start"])
    parts, col = [], 0
    for hd in heads:
        s, e, act = hd["start"], hd["end"], hd["act"]
        if not (col <= s < e <= width):
            raise CaseError(f"case.json: head [{s}, {e}) overlaps another or leaves the {width} output columns")
        if s > col:
            parts.append(h[:, col:s])
        z = h[:, s:e]
        if act == "identity":
            parts.append(z)
        elif act == "sigmoid":
            parts.append(torch.sigmoid(z))
        elif act == "exp":
            parts.append(torch.exp(z))
        elif act == "softmax":
            parts.append(torch.softmax(z / float(hd["temperature"]), dim=-1))
        else:
            raise CaseError(f"case.json: head [{s}, {e}): unknown activation '{act}'")
        col = e
    if col < width:
        parts.append(h[:, col:])
    y = torch.cat(parts, dim=-1)
    gy = load(d, "gy", (n, width))
    (y * gy).sum().backward()
    save(d, "y", y)
    save(d, "gx", grad_or_zeros(x))
    for i, (lin, _) in enumerate(layers):
        if hasattr(lin, "parametrizations"):
            save(d, f"gw{i}", grad_or_zeros(lin.parametrizations.weight.original1))
            save(d, f"gg{i}", grad_or_zeros(lin.parametrizations.weight.original0).view(-1))
            save(d, f"gb{i}", grad_or_zeros(lin.bias))
            continue
        save(d, f"gw{i}", grad_or_zeros(lin.weight))
        save(d, f"gb{i}", grad_or_zeros(lin.bias))


def op_triplane(d, case):
    planes = load(d, "planes", (3, None, None, None))
    r, r2, c = planes.shape[1:]
    if r != r2:
        raise CaseError(f"{os.path.join(d, 'planes.npy')}: planes are {r}x{r2}, expected square")
    planes.requires_grad_(True)
    points = load(d, "points", (None, 3)).requires_grad_(True)
    n = points.shape[0]
    lo = torch.tensor([float(v) for v in case["box_min"]])
    hi = torch.tensor([float(v) for v in case["box_max"]])
    if lo.shape != (3,) or hi.shape != (3,):
        raise CaseError("case.json: box_min and box_max need 3 numbers each")
    u = (points - lo) / (hi - lo) * 2.0 - 1.0
    feats = []
    for p, (ax, ay) in enumerate([(0, 1), (0, 2), (1, 2)]):
        plane = planes[p].permute(2, 0, 1).unsqueeze(0)  # (1, C, R, R): dim 2 is y (row), dim 3 is x (col)
        grid = torch.stack([u[:, ax], u[:, ay]], dim=-1).reshape(1, 1, n, 2)  # (..., 0) = x, (..., 1) = y
        f = F.grid_sample(plane, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        feats.append(f[0, :, 0, :].transpose(0, 1))  # (n, C)
    feat = torch.cat(feats, dim=-1)
    gfeat = load(d, "gfeat", (n, 3 * c))
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
    r6 = load(d, "r6", (None, 6)).requires_grad_(True)
    r = rotation_6d_to_matrix(r6)
    (r * load(d, "gR", (r6.shape[0], 3, 3))).sum().backward()
    save(d, "R", r)
    save(d, "gr6", grad_or_zeros(r6))


def batch_rodrigues(r):
    """smplx's batch_rodrigues (axis-angle -> rotation matrix), without its 1e-8 guard
    (the cases have no zero rotations)."""
    angle = torch.norm(r, dim=1, keepdim=True)
    k = r / angle
    cos, sin = torch.cos(angle)[:, :, None], torch.sin(angle)[:, :, None]
    z = torch.zeros_like(k[:, 0])
    skew = torch.stack((z, -k[:, 2], k[:, 1], k[:, 2], z, -k[:, 0], -k[:, 1], k[:, 0], z), dim=1).view(-1, 3, 3)
    eye = torch.eye(3)[None]
    return eye + sin * skew + (1 - cos) * torch.bmm(skew, skew)


def op_pose_blend(d, case):
    pose = load(d, "pose", (24, 3))
    basis = load(d, "basis", (None, 207, 3)).requires_grad_(True)
    n = basis.shape[0]
    decoded = load(d, "decoded", (n, 3))
    # SMPL's pose feature: (R_j - I) of joints 1-23, flattened.
    features = (batch_rodrigues(pose[1:]) - torch.eye(3)[None]).reshape(-1)
    offsets = decoded + torch.einsum("nka,k->na", basis, features)
    (offsets * load(d, "g", (n, 3))).sum().backward()
    save(d, "features", features)
    save(d, "offsets", offsets)
    save(d, "gbasis", grad_or_zeros(basis))


def quat_to_matrix(q):
    """(w, x, y, z) -> rotation, the splatter's formula (unit quaternions)."""
    w, x, y, z = q.unbind(-1)
    rows = [
        torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)), -1),
        torch.stack((2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)), -1),
        torch.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), -1),
    ]
    return torch.stack(rows, -2)


def matrix_to_quat_unnormalised(m):
    """Shepperd's method without the final normalisation: the candidate of the largest
    of (trace, m00, m11, m22), the first one on ties (drape's rule; the blended rotation
    is not orthogonal, so the branch decides the value)."""
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cands = torch.stack(
        (
            torch.stack((1 + tr, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]), -1),
            torch.stack((m[:, 2, 1] - m[:, 1, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]), -1),
            torch.stack((m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0], 1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], m[:, 1, 2] + m[:, 2, 1]), -1),
            torch.stack((m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1], 1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]), -1),
        ),
        1,
    )
    keys = torch.stack((tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]), -1).detach()
    branch = torch.zeros(m.shape[0], dtype=torch.long)
    best = keys[:, 0].clone()
    for i in range(1, 4):
        better = keys[:, i] > best
        branch = torch.where(better, torch.full_like(branch, i), branch)
        best = torch.where(better, keys[:, i], best)
    return cands[torch.arange(m.shape[0]), branch]


def op_deform(d, case):
    """HUGS's skinning of a decoded Gaussian, by autograd: posed mean
    x + sum_j w_j (A_j [x; 1] - x) with x = mean + offset, posed rotation
    (sum_j w_j R_j) R_q R_6d as an unnormalised quaternion, log-scale + delta."""
    transforms = load(d, "transforms", (24, 3, 4)).requires_grad_(True)
    means = load(d, "means", (None, 3)).requires_grad_(True)
    n = means.shape[0]
    quats = load(d, "quats", (n, 4))
    offsets = load(d, "offsets", (n, 3)).requires_grad_(True)
    rot6d = load(d, "rot6d", (n, 6)).requires_grad_(True)
    log_scales = load(d, "log_scales", (n, 3))
    deltas = load(d, "log_scale_deltas", (n, 3)).requires_grad_(True)
    weights = load(d, "weights", (n, 24)).requires_grad_(True)
    x = means + offsets
    rot, trans = transforms[:, :, :3], transforms[:, :, 3]
    ax = torch.einsum("jab,nb->nja", rot, x) + trans[None]
    mean = x + torch.einsum("nj,nja->na", weights, ax - x[:, None, :])
    blended = torch.einsum("nj,jab->nab", weights, rot)
    posed = blended @ quat_to_matrix(quats) @ rotation_6d_to_matrix(rot6d)
    quat = matrix_to_quat_unnormalised(posed)
    log_scale = log_scales + deltas
    loss = (mean * load(d, "g_mean", (n, 3))).sum() + (quat * load(d, "g_quat", (n, 4))).sum() + (log_scale * load(d, "g_log_scale", (n, 3))).sum()
    loss.backward()
    save(d, "mean", mean)
    save(d, "quat", quat)
    for name, t in [("transforms", transforms), ("means", means), ("offsets", offsets), ("rot6d", rot6d), ("log_scale_deltas", deltas), ("weights", weights)]:
        save(d, "g" + name, grad_or_zeros(t))


def gaussian_window(size, sigma):
    """pytorch_msssim's _fspecial_gauss_1d, but in float64 (it builds float32)."""
    coords = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(coords**2) / (2 * sigma**2))
    return (g / g.sum()).reshape(1, 1, size)


def op_ssim(d, case):
    from pytorch_msssim import ssim

    win_size, win_sigma = 11, 1.5
    img1 = load(d, "img1", (None, None, 3))
    h, w = img1.shape[:2]
    if h < win_size or w < win_size:
        # pytorch_msssim would skip the blur along that axis (with a warning).
        raise CaseError(f"{os.path.join(d, 'img1.npy')}: {h}x{w} is smaller than the {win_size}-tap window")
    img2 = load(d, "img2", (h, w, 3))
    a = img1.permute(2, 0, 1).unsqueeze(0).contiguous().requires_grad_(True)  # (1, 3, H, W)
    b = img2.permute(2, 0, 1).unsqueeze(0).contiguous()
    win = gaussian_window(win_size, win_sigma).repeat(3, 1, 1, 1)  # (3, 1, 1, 11), as ssim() makes it
    s = ssim(a, b, data_range=1.0, size_average=True, win=win, K=(0.01, 0.03))
    if s.dtype != torch.float64:
        raise CaseError(f"ssim: pytorch_msssim computed in {s.dtype}")
    s.backward()
    save(d, "ssim", s.reshape(1))
    save(d, "gimg1", grad_or_zeros(a)[0].permute(1, 2, 0))


def op_l1(d, case):
    a = load(d, "a")
    b = load(d, "b", tuple(a.shape))
    a.requires_grad_(True)
    loss = F.l1_loss(a, b)
    loss.backward()
    save(d, "loss", loss.reshape(1))
    save(d, "ga", grad_or_zeros(a))


def op_chamfer(d, case):
    """Bidirectional Chamfer through Geman-McClure (torch.cdist, min, autograd)."""
    p = load(d, "pred", (None, 3))
    q = load(d, "target", (None, 3))
    sigma = float(case["sigma"])
    p.requires_grad_(True)
    d2 = torch.cdist(p, q) ** 2
    rho = lambda x: x / (x + sigma**2)
    loss = 0.5 * (rho(d2.min(dim=1).values).mean() + rho(d2.min(dim=0).values).mean())
    loss.backward()
    save(d, "loss", loss.reshape(1))
    save(d, "gpred", grad_or_zeros(p))


def op_arap(d, case):
    """Variance (population) of the edge lengths, with autograd."""
    v = load(d, "positions", (None, 3))
    e = load(d, "edges", (None, 2)).long()
    v.requires_grad_(True)
    lengths = (v[e[:, 0]] - v[e[:, 1]]).norm(dim=1)
    loss = lengths.var(unbiased=False)
    loss.backward()
    save(d, "loss", loss.reshape(1))
    save(d, "gpositions", grad_or_zeros(v))


def op_lpips(d, case):
    """The `lpips` package with a seeded random backbone: its weights written by
    scripts/lpips-to-safetensors.py's functions, LPIPS(img0, img1, normalize=True)
    and its gradient to img0 by autograd."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("lpips_convert", case["converter"])
    conv = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conv)
    from safetensors.torch import save_file

    model = conv.build(case["net"], int(case["seed"])).double()
    save_file(conv.state(model), os.path.join(d, "weights.safetensors"))
    a = load(d, "img0", (None, None, 3)).permute(2, 0, 1).unsqueeze(0).contiguous()
    b = load(d, "img1", tuple(a.shape[2:]) + (3,)).permute(2, 0, 1).unsqueeze(0).contiguous()
    a.requires_grad_(True)
    v = model(a, b, normalize=True).sum()
    v.backward()
    save(d, "lpips", v.reshape(1))
    save(d, "gimg0", grad_or_zeros(a)[0].permute(1, 2, 0))


OPS = {"lpips": op_lpips, "mlp": op_mlp, "triplane": op_triplane, "rot6d": op_rot6d, "ssim": op_ssim, "l1": op_l1, "chamfer": op_chamfer, "arap": op_arap, "pose_blend": op_pose_blend, "deform": op_deform}


def main():
    if len(sys.argv) != 2:
        print("usage: torch_reference.py CASE_DIR", file=sys.stderr)
        return 1
    d = sys.argv[1]
    op = "?"
    try:
        path = os.path.join(d, "case.json")
        try:
            with open(path) as f:
                case = json.load(f)
        except Exception as e:
            raise CaseError(f"{path}: {e}") from None
        op = str(case.get("op", "?"))
        if op not in OPS:
            raise CaseError(f"{path}: unknown op '{op}' (known: {', '.join(OPS)})")
        OPS[op](d, case)
    except CaseError as e:
        print(" ".join(f"torch_reference: {op}: {e}".split()), file=sys.stderr)
        return 1
    except Exception as e:  # a missing key, a PyTorch error: still one line, naming the case
        msg = f"torch_reference: {op}: {d}: {type(e).__name__}: {e}"
        print(" ".join(msg.split()), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
