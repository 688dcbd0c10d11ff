#!/usr/bin/env python3
"""Converts pytorch-fid's FID Inception weights (the TensorFlow FID graph's Inception,
ported by pytorch-fid: pt_inception-2015-12-05-6726825d.pth) to the safetensors file
drape reads (`drape eval --fid-weights FILE`).

    python3 scripts/fid-to-safetensors.py [--pth FILE] OUT.safetensors

needs `pip install torch torchvision safetensors`. With `--pth`, the .pth file
pytorch-fid downloads (its FID_WEIGHTS_URL; pytorch-fid keeps it in torch's hub cache,
~/.cache/torch/hub/checkpoints/); without it, the same URL through torch's hub cache
(downloaded on first use). `--random SEED` writes seeded random weights instead (no
download; what drape's tests compare against).

The weights are loaded, strictly, into torchvision's Inception-v3 with pytorch-fid's FID
blocks (`fid_inception_v3()` below, as pytorch_fid.inception builds it), so a file with
other names or shapes fails here. The file holds that network's state dict as float32:
`NAME.conv.weight` and `NAME.bn.weight|bias|running_mean|running_var` for every
BasicConv2d; the classifier (`fc.*`) and `num_batches_tracked` are left out.
"""
import argparse
import sys

FID_WEIGHTS_URL = "https://github.com/mseitzer/pytorch-fid/releases/download/fid_weights/pt_inception-2015-12-05-6726825d.pth"


def fid_blocks():
    """pytorch-fid's FIDInceptionA/C/E_1/E_2 (pytorch_fid/inception.py, 0.3.0): torchvision's
    blocks with the average pool not counting the padding, and E_2 max-pooling."""
    import torch
    import torch.nn.functional as F
    from torchvision.models.inception import InceptionA, InceptionC, InceptionE

    class FIDInceptionA(InceptionA):
        def forward(self, x):
            branch1x1 = self.branch1x1(x)
            branch5x5 = self.branch5x5_2(self.branch5x5_1(x))
            branch3x3dbl = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
            branch_pool = self.branch_pool(F.avg_pool2d(x, kernel_size=3, stride=1, padding=1, count_include_pad=False))
            return torch.cat([branch1x1, branch5x5, branch3x3dbl, branch_pool], 1)

    class FIDInceptionC(InceptionC):
        def forward(self, x):
            branch1x1 = self.branch1x1(x)
            branch7x7 = self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x)))
            branch7x7dbl = self.branch7x7dbl_1(x)
            branch7x7dbl = self.branch7x7dbl_2(branch7x7dbl)
            branch7x7dbl = self.branch7x7dbl_3(branch7x7dbl)
            branch7x7dbl = self.branch7x7dbl_4(branch7x7dbl)
            branch7x7dbl = self.branch7x7dbl_5(branch7x7dbl)
            branch_pool = self.branch_pool(F.avg_pool2d(x, kernel_size=3, stride=1, padding=1, count_include_pad=False))
            return torch.cat([branch1x1, branch7x7, branch7x7dbl, branch_pool], 1)

    class FIDInceptionE_1(InceptionE):
        def forward(self, x):
            branch1x1 = self.branch1x1(x)
            b3 = self.branch3x3_1(x)
            branch3x3 = torch.cat([self.branch3x3_2a(b3), self.branch3x3_2b(b3)], 1)
            bd = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
            branch3x3dbl = torch.cat([self.branch3x3dbl_3a(bd), self.branch3x3dbl_3b(bd)], 1)
            branch_pool = self.branch_pool(F.avg_pool2d(x, kernel_size=3, stride=1, padding=1, count_include_pad=False))
            return torch.cat([branch1x1, branch3x3, branch3x3dbl, branch_pool], 1)

    class FIDInceptionE_2(InceptionE):
        def forward(self, x):
            branch1x1 = self.branch1x1(x)
            b3 = self.branch3x3_1(x)
            branch3x3 = torch.cat([self.branch3x3_2a(b3), self.branch3x3_2b(b3)], 1)
            bd = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
            branch3x3dbl = torch.cat([self.branch3x3dbl_3a(bd), self.branch3x3dbl_3b(bd)], 1)
            # The FID graph max-pools here (pytorch-fid keeps the quirk).
            branch_pool = self.branch_pool(F.max_pool2d(x, kernel_size=3, stride=1, padding=1))
            return torch.cat([branch1x1, branch3x3, branch3x3dbl, branch_pool], 1)

    return FIDInceptionA, FIDInceptionC, FIDInceptionE_1, FIDInceptionE_2


def fid_inception_v3():
    """torchvision's Inception-v3 patched as pytorch_fid.inception.fid_inception_v3(),
    without loading weights."""
    import torchvision

    A, C, E1, E2 = fid_blocks()
    inception = torchvision.models.inception_v3(weights=None, aux_logits=False, init_weights=False, num_classes=1008)
    inception.Mixed_5b = A(192, pool_features=32)
    inception.Mixed_5c = A(256, pool_features=64)
    inception.Mixed_5d = A(288, pool_features=64)
    inception.Mixed_6b = C(768, channels_7x7=128)
    inception.Mixed_6c = C(768, channels_7x7=160)
    inception.Mixed_6d = C(768, channels_7x7=160)
    inception.Mixed_6e = C(768, channels_7x7=192)
    inception.Mixed_7b = E1(1280)
    inception.Mixed_7c = E2(2048)
    return inception


def randomize(inception, seed):
    """Seeded weights that keep activations of order one through the ~95 layers (He
    normal convolutions; batchnorm statistics and affine parameters away from the
    identity, so that folding them is exercised)."""
    import math

    import torch
    from torchvision.models.inception import BasicConv2d

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in inception.modules():
            if isinstance(m, BasicConv2d):
                w = m.conv.weight
                fan_in = w.shape[1] * w.shape[2] * w.shape[3]
                w.copy_(torch.randn(w.shape, generator=g) * math.sqrt(2.0 / fan_in))
                n = w.shape[0]
                m.bn.weight.copy_(0.5 + torch.rand(n, generator=g))
                m.bn.bias.copy_(0.4 * torch.rand(n, generator=g) - 0.2)
                m.bn.running_mean.copy_(0.4 * torch.rand(n, generator=g) - 0.2)
                m.bn.running_var.copy_(0.5 + torch.rand(n, generator=g))
    return inception


def build(pth=None, random_seed=None):
    """The FID Inception in eval mode with pytorch-fid's weights (from `pth`, else its
    URL through torch's hub cache) or seeded random ones."""
    import torch

    inception = fid_inception_v3()
    if random_seed is not None:
        randomize(inception, random_seed)
    else:
        if pth is not None:
            state_dict = torch.load(pth, map_location="cpu", weights_only=True)
        else:
            state_dict = torch.hub.load_state_dict_from_url(FID_WEIGHTS_URL, map_location="cpu", progress=True)
        inception.load_state_dict(state_dict, strict=True)
    return inception.eval()


def pool3(inception, x):
    """pytorch_fid.inception.InceptionV3([3])(x)[0] flattened: x is B x 3 x H x W in
    [0, 1]; resized to 299 x 299 (bilinear, align_corners=False), scaled to [-1, 1], the
    blocks up to Mixed_7c, then the adaptive average pool. (B, 2048)."""
    import torch.nn.functional as F

    x = F.interpolate(x, size=(299, 299), mode="bilinear", align_corners=False)
    x = 2 * x - 1
    x = inception.Conv2d_2b_3x3(inception.Conv2d_2a_3x3(inception.Conv2d_1a_3x3(x)))
    x = F.max_pool2d(x, kernel_size=3, stride=2)
    x = inception.Conv2d_4a_3x3(inception.Conv2d_3b_1x1(x))
    x = F.max_pool2d(x, kernel_size=3, stride=2)
    for name in ["Mixed_5b", "Mixed_5c", "Mixed_5d", "Mixed_6a", "Mixed_6b", "Mixed_6c", "Mixed_6d", "Mixed_6e", "Mixed_7a", "Mixed_7b", "Mixed_7c"]:
        x = getattr(inception, name)(x)
    return F.adaptive_avg_pool2d(x, output_size=(1, 1)).flatten(1)


def state(inception):
    return {k: v.detach().float().contiguous() for k, v in inception.state_dict().items() if not k.startswith("fc.") and not k.endswith("num_batches_tracked")}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pth", help="pytorch-fid's pt_inception-2015-12-05-6726825d.pth (default: its URL via torch's hub cache)")
    ap.add_argument("--random", type=int, metavar="SEED", help="seeded random weights instead of the pretrained ones")
    ap.add_argument("out")
    a = ap.parse_args()
    from safetensors.torch import save_file

    save_file(state(build(a.pth, a.random)), a.out)
    print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
