"""Case directories shared by the reference scripts: NAME.npy in and out as float64
tensors, and the one error a bad case raises (the script prints it in one line)."""

import os

import numpy as np
import torch


class CaseError(Exception):
    pass


def load(d, name, shape=None):
    """Loads NAME.npy as a float64 tensor; `shape` entries that are None match anything."""
    path = os.path.join(d, name + ".npy")
    try:
        a = np.load(path, allow_pickle=False)
    except Exception as e:
        raise CaseError(f"{path}: cannot read: {e}") from None
    if shape is not None:
        ok = a.ndim == len(shape) and all(s is None or s == t for s, t in zip(shape, a.shape))
        if not ok:
            want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
            raise CaseError(f"{path}: shape {a.shape}, expected {want}")
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))


def save(d, name, t):
    a = np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)
    np.save(os.path.join(d, name + ".npy"), a)


def grad_or_zeros(t):
    return t.grad if t.grad is not None else torch.zeros_like(t)
