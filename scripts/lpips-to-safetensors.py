#!/usr/bin/env python3
"""Converts LPIPS v0.1 (the `lpips` package: its learned linear layers, shipped with the
package, and the torchvision backbone) to the safetensors file drape reads
(`--lpips-weights FILE`).

    python3 scripts/lpips-to-safetensors.py --net alex OUT.safetensors

needs `pip install lpips torchvision safetensors` and, for the pretrained backbone,
torchvision's AlexNet or VGG16 ImageNet weights (downloaded by torchvision on first use,
or already in its cache). `--random-backbone SEED` uses a seeded random backbone
instead (no download; what drape's tests compare against).

The file holds the package's state dict as float32: `net.sliceS.I.weight|bias` for
each convolution and `linL.model.1.weight` for each tapped layer.
"""
import argparse
import sys


def build(net, random_backbone_seed=None):
    import lpips
    import torch

    if random_backbone_seed is not None:
        torch.manual_seed(random_backbone_seed)
    model = lpips.LPIPS(net=net, version="0.1", pretrained=True, pnet_rand=random_backbone_seed is not None, verbose=False)
    return model.eval()


def state(model):
    return {k: v.detach().float().contiguous() for k, v in model.state_dict().items() if k.startswith("net.") or k.startswith("lin")}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--net", choices=["alex", "vgg"], default="alex")
    ap.add_argument("--random-backbone", type=int, metavar="SEED", help="a seeded random backbone instead of the pretrained one")
    ap.add_argument("out")
    a = ap.parse_args()
    from safetensors.torch import save_file

    save_file(state(build(a.net, a.random_backbone)), a.out)
    print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
