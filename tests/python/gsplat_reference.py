"""gsplat's PyTorch implementation (CPU, float64) as the reference for drape's splatter.

Usage: python gsplat_reference.py CASE_DIR [CASE_DIR ...]

Each CASE_DIR holds case.json and the inputs as float64 .npy files (C order); the
outputs are written there as float64, C-order .npy files. One process serves several
cases so that torch is imported once. Exit status 0, or 1 with one line on stderr
naming the case directory and the file at fault.

case.json: {"width": W, "height": H, "sh_degree": D, "mode": "classic" | "antialiased",
            "near": n, "far": f, "eps2d": 0.3, "tile_size": 16}
Inputs:  means (N, 3), quats (N, 4) as (w, x, y, z), log_scales (N, 3),
         opacity_logits (N,), sh (N, K, 3) with K = (D + 1)^2, viewmat (4, 4)
         world-to-camera (OpenCV: x right, y down, z forward), K (3, 3), background (3,),
         w_rgb (H, W, 3), w_alpha (H, W), w_depth (H, W).
Outputs: rgb (H, W, 3), alpha (H, W), depth (H, W) = sum of w_i z_i (gsplat's
         render_mode "RGB+D": depth composited as a fourth channel over a 0 background);
         per Gaussian means2d (N, 2), depths (N,), conics (N, 3), opacities (N,) (after
         the compensation in antialiased mode), colors (N, 3), radii (N, 2) of the torch
         projection (ceil(3.33 sigma)), and radii_cuda (N, 2) with radius_arg (N, 2): the
         opacity-aware rule of gsplat's CUDA projection (ProjectionEWA3DGSFused.cu) on the
         same covariance, ceil(min(3.33, sqrt(2 ln(o / (1/255)))) * sqrt(cov_ii)), 0 when
         o < 1/255, off the image or culled, with the value before the ceil; done (H, W)
         1 where the transmittance stop ended the pixel, clamped (H, W) the number of
         its blended splats whose alpha was clamped at 0.999;
         gradients of sum(rgb * w_rgb) + sum(alpha * w_alpha) + sum(depth * w_depth) to
         means, quats, log_scales, opacity_logits and sh (same shapes as the inputs).

What is gsplat's and what is written here. gsplat 1.5's `_rasterization` needs CUDA
(its `isect_tiles`, `spherical_harmonics` and `rasterize_to_indices_in_range` are
CUDA kernels, and `accumulate` needs nerfacc's CUDA scans), so only its pure-torch
pieces run here: `_quat_scale_to_covar_preci`, `_fully_fused_projection` (world to
camera, the clamped perspective Jacobian, the eps2d blur, the compensation, conics,
radii), `_spherical_harmonics`, `_isect_tiles` and `_isect_offset_encode` (each
tile's Gaussians in depth order). The per-pixel compositing is gsplat's
`rasterize_to_pixels_3dgs_fwd` kernel transcribed into dense torch over each tile's
list: pixel centres at (i + 0.5, j + 0.5), sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,
alpha = min(0.999, o e^-sigma), skipped when sigma < 0 or alpha < 1/255, and the pixel
done (exclusive) at the first splat that would take T to 1e-4 or below; the gradient
is autograd's through that.
"""

import json
import math
import os
import sys

import numpy as np
import torch

from case_io import CaseError, grad_or_zeros, load, save  # tests/python/case_io.py

torch.set_default_dtype(torch.float64)

# gsplat's CUDA constants, as float32 (Common.h, RasterizeToPixels3DGSFwd.cu).
ALPHA_THRESHOLD = float(np.float32(1.0 / 255.0))
ALPHA_MAX = float(np.float32(0.999))
T_MIN = float(np.float32(1e-4))


def composite(means2d, conics, opacities, colors, background, flatten_ids, offsets, width, height, tile_size):
    """gsplat's forward rasterizer per tile, dense: colors (N, C) over background (C,).
    Returns the image (H, W, C), the alpha (H, W), and for the test's coverage checks
    whether each pixel was ended by the transmittance stop and how many of its splats
    were clamped at ALPHA_MAX (H, W)."""
    tiles_y, tiles_x = offsets.shape
    starts = offsets.flatten().tolist() + [len(flatten_ids)]
    channels = colors.shape[1]
    image = torch.zeros(height, width, channels)
    alpha_img = torch.zeros(height, width)
    done = torch.zeros(height, width)
    clamped = torch.zeros(height, width)
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            t = ty * tiles_x + tx
            x0, y0 = tx * tile_size, ty * tile_size
            x1, y1 = min(x0 + tile_size, width), min(y0 + tile_size, height)
            ids = flatten_ids[starts[t] : starts[t + 1]].long()
            if len(ids) == 0:
                image[y0:y1, x0:x1] = background
                continue
            py, px = torch.meshgrid(torch.arange(y0, y1) + 0.5, torch.arange(x0, x1) + 0.5, indexing="ij")
            pix = torch.stack([px.flatten(), py.flatten()], dim=-1)  # (P, 2)
            delta = means2d[ids][None, :, :] - pix[:, None, :]  # (P, K, 2)
            c = conics[ids]
            sigma = 0.5 * (c[None, :, 0] * delta[..., 0] ** 2 + c[None, :, 2] * delta[..., 1] ** 2) + c[None, :, 1] * delta[..., 0] * delta[..., 1]
            alpha = torch.clamp_max(opacities[ids][None, :] * torch.exp(-sigma), ALPHA_MAX)
            with torch.no_grad():
                keep = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
                # T after each kept splat; the first splat that would take it to T_MIN
                # or below ends the pixel, and T only falls, so every later one is out.
                t_incl = torch.cumprod(1.0 - torch.where(keep, alpha, torch.zeros_like(alpha)), dim=1)
                blend = keep & (t_incl > T_MIN)
                done[y0:y1, x0:x1] = (keep & (t_incl <= T_MIN)).any(dim=1).double().reshape(y1 - y0, x1 - x0)
                raw = opacities[ids][None, :] * torch.exp(-sigma)
                clamped[y0:y1, x0:x1] = (blend & (raw > ALPHA_MAX)).sum(dim=1).double().reshape(y1 - y0, x1 - x0)
            a = torch.where(blend, alpha, torch.zeros_like(alpha))
            trans = torch.cumprod(1.0 - a, dim=1)
            t_excl = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1)
            w = a * t_excl  # (P, K)
            t_final = trans[:, -1]
            pix_col = w @ colors[ids] + t_final[:, None] * background[None, :]
            image[y0:y1, x0:x1] = pix_col.reshape(y1 - y0, x1 - x0, channels)
            alpha_img[y0:y1, x0:x1] = (1.0 - t_final).reshape(y1 - y0, x1 - x0)
    return image, alpha_img, done, clamped


def run_case(d):
    try:
        from gsplat.cuda._torch_impl import (
            _fully_fused_projection,
            _isect_offset_encode,
            _isect_tiles,
            _persp_proj,
            _quat_scale_to_covar_preci,
            _spherical_harmonics,
            _world_to_cam,
        )
    except ImportError as e:
        raise CaseError(f"gsplat is not installed in this environment ({e}): run scripts/torch-env.sh") from None

    path = os.path.join(d, "case.json")
    try:
        with open(path) as f:
            case = json.load(f)
    except Exception as e:
        raise CaseError(f"{path}: {e}") from None
    width, height = int(case["width"]), int(case["height"])
    degree = int(case["sh_degree"])
    mode = case["mode"]
    if mode not in ("classic", "antialiased"):
        raise CaseError(f"{path}: unknown mode '{mode}'")
    near, far, eps2d = float(case["near"]), float(case["far"]), float(case["eps2d"])
    tile_size = int(case["tile_size"])

    means = load(d, "means", (None, 3)).requires_grad_(True)
    n = means.shape[0]
    quats = load(d, "quats", (n, 4)).requires_grad_(True)
    log_scales = load(d, "log_scales", (n, 3)).requires_grad_(True)
    logits = load(d, "opacity_logits", (n,)).requires_grad_(True)
    sh = load(d, "sh", (n, (degree + 1) ** 2, 3)).requires_grad_(True)
    viewmat = load(d, "viewmat", (4, 4))[None]
    ks = load(d, "K", (3, 3))[None]
    background = load(d, "background", (3,))
    w_rgb = load(d, "w_rgb", (height, width, 3))
    w_alpha = load(d, "w_alpha", (height, width))
    w_depth = load(d, "w_depth", (height, width))

    # Projection: gsplat's functions, as `_rasterization` calls them.
    scales = torch.exp(log_scales)
    covars, _ = _quat_scale_to_covar_preci(quats, scales, True, False, triu=False)
    radii, means2d, depths, conics, comp = _fully_fused_projection(
        means, covars, viewmat, ks, width, height, eps2d=eps2d, near_plane=near, far_plane=far, calc_compensations=(mode == "antialiased")
    )
    radii, means2d, depths, conics = radii[0], means2d[0], depths[0], conics[0]
    opacities = torch.sigmoid(logits)
    if comp is not None:
        opacities = opacities * comp[0]

    # Colour: SH at the direction from the camera centre, + 0.5, clamped at 0.
    campos = torch.inverse(viewmat[0])[:3, 3]
    colors = torch.clamp_min(_spherical_harmonics(degree, means - campos, sh) + 0.5, 0.0)

    # The CUDA kernel's opacity-aware radius on the same (blurred) covariance.
    with torch.no_grad():
        means_c, covars_c = _world_to_cam(means, covars, viewmat)
        _, cov2d = _persp_proj(means_c, covars_c, ks, width, height)
        cov2d = cov2d[0] + eps2d * torch.eye(2)
        diag = torch.stack([cov2d[:, 0, 0], cov2d[:, 1, 1]], dim=-1)
        o = opacities.detach()
        extend = torch.sqrt(2.0 * torch.log(torch.clamp_min(o, ALPHA_THRESHOLD) / ALPHA_THRESHOLD)).clamp_max(3.33)
        radius_arg = extend[:, None] * torch.sqrt(diag)
        r = torch.ceil(radius_arg)
        det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
        m = means2d.detach()
        ok = (det > 0) & (depths > near) & (depths < far) & (o >= ALPHA_THRESHOLD) & ((r[:, 0] > 0) | (r[:, 1] > 0))
        ok &= (m[:, 0] + r[:, 0] > 0) & (m[:, 0] - r[:, 0] < width) & (m[:, 1] + r[:, 1] > 0) & (m[:, 1] - r[:, 1] < height)
        radii_cuda = torch.where(ok[:, None], r, torch.zeros_like(r))

    # Tile lists: gsplat's binning of its torch radii, each tile in depth order.
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    _, isect_ids, flatten_ids = _isect_tiles(means2d[None].detach(), radii[None], depths[None].detach(), tile_size, tiles_x, tiles_y)
    offsets = _isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)[0]

    # "RGB+D": the depth is a fourth channel composited over a 0 background.
    rgbd, alpha, done, clamped = composite(
        means2d, conics, opacities, torch.cat([colors, depths[:, None]], dim=-1), torch.cat([background, torch.zeros(1)]), flatten_ids, offsets, width, height, tile_size
    )
    rgb, depth = rgbd[..., :3], rgbd[..., 3]
    ((rgb * w_rgb).sum() + (alpha * w_alpha).sum() + (depth * w_depth).sum()).backward()

    for name, t in [("rgb", rgb), ("alpha", alpha), ("depth", depth), ("means2d", means2d), ("depths", depths), ("conics", conics), ("opacities", opacities), ("colors", colors), ("radii", radii.double()), ("radii_cuda", radii_cuda), ("radius_arg", radius_arg), ("done", done), ("clamped", clamped)]:
        save(d, name, t)
    for name, t in [("gmeans", means), ("gquats", quats), ("glog_scales", log_scales), ("gopacity_logits", logits), ("gsh", sh)]:
        save(d, name, grad_or_zeros(t))


def main():
    if len(sys.argv) < 2:
        print("usage: gsplat_reference.py CASE_DIR [CASE_DIR ...]", file=sys.stderr)
        return 1
    for d in sys.argv[1:]:
        try:
            run_case(d)
        except CaseError as e:
            print(" ".join(f"gsplat_reference: {d}: {e}".split()), file=sys.stderr)
            return 1
        except Exception as e:  # a missing key, a PyTorch error: still one line, naming the case
            msg = f"gsplat_reference: {d}: {type(e).__name__}: {e}"
            print(" ".join(msg.split()), file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
