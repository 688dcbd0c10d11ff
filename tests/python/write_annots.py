"""ZJU-MoCap annotations as scripts write them, with real numpy, for the pickle
reader's tests.

Usage: write_annots.py OUT_DIR

For every case OUT_DIR/<case>/ holds `annots.npy` (a dict: `cams` with lists `K`
(3x3), `D` (5x1), `R` (3x3), `T` (3x1, millimetres), one array per camera; `ims`, per
frame a dict whose `ims` lists one image path per camera) and `smpl_params/{0,1}.npy`
(dicts of `poses` 1x72, `Rh` 1x3, `Th` 1x3, `shapes` 1x10), built the way such scripts
build them: `np.array` of lists of floats, `np.zeros((5, 1))` for an undistorted
camera, one zeros array shared by two cameras, a transposed rotation (Fortran order)
and a translation sliced from a 4x4 extrinsic matrix (neither C-contiguous).

Cases: `<dtype>_<how>`. dtype: f64, f32, or mixed (K and R float64, D and T float32;
poses float32, the rest float64). how: `save` (np.save, numpy's own protocol) or
`p2`..`p5` (the .npy header np.save writes, then pickle.dump with that protocol: what
np.lib.format.write_array does, whose protocol is fixed, 3 in numpy 1.x and 4 in 2.x).
Module paths follow the numpy that runs this (`numpy.core` in 1.x, `numpy._core` in
2.x). Every file is loaded back with np.load to check that numpy itself reads it.

What the files hold, as float64 (values after the cast to the case's dtype, so exact):
OUT_DIR/<case>/expected/{K,D,R,T}.npy stacked per camera (T in millimetres as stored),
expected/smpl{0,1}_{poses,Rh,Th,shapes}.npy, and expected/ims.txt (one line per frame,
the camera paths separated by tabs). OUT_DIR/cases.txt lists the cases.
"""

import os
import pickle
import sys

import numpy as np

out = sys.argv[1]
os.makedirs(out, exist_ok=True)
rng = np.random.default_rng(46)
CAMERAS = 4
FRAMES = 5


def rotation(axis, angle):
    """Rodrigues' formula, a proper rotation as nested Python floats."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    r = np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
    return r.tolist()


# The numbers, as Python floats (what a script reads from a calibration file).
Ks = [[[1120.5 + 3.25 * c, 0.0, 511.75 - c], [0.0, 1119.125 + 2.5 * c, 512.5 + 0.5 * c], [0.0, 0.0, 1.0]] for c in range(CAMERAS)]
Ds = [None, None, [-0.3121, 0.1057, 0.00043, -0.00071, -0.0125], None]  # None: np.zeros((5, 1))
Rs = [rotation(rng.normal(size=3), rng.uniform(0.2, 2.5)) for _ in range(CAMERAS)]
Ts = [[float(v) for v in rng.uniform(-2500.0, 2500.0, size=3)] for _ in range(CAMERAS)]
Ts[1][2] = 3000.0 + 1.0 / 3.0
ims = [[f"Camera_B{c + 1}/{f:06d}.jpg" for c in range(CAMERAS)] for f in range(FRAMES)]
smpl = [
    {
        "poses": rng.uniform(-0.5, 0.5, size=(1, 72)).tolist(),
        "Rh": rng.uniform(-3.0, 3.0, size=(1, 3)).tolist(),
        "Th": rng.uniform(-1.0, 1.0, size=(1, 3)).tolist(),
        "shapes": rng.normal(size=(1, 10)).tolist(),
    }
    for _ in range(2)
]

DTYPES = {
    "f64": dict(K=np.float64, D=np.float64, R=np.float64, T=np.float64, poses=np.float64, rest=np.float64),
    "f32": dict(K=np.float32, D=np.float32, R=np.float32, T=np.float32, poses=np.float32, rest=np.float32),
    "mixed": dict(K=np.float64, D=np.float32, R=np.float64, T=np.float32, poses=np.float32, rest=np.float64),
}


def annots(types):
    cams = {"K": [], "D": [], "R": [], "T": []}
    shared_zeros = np.zeros((5, 1), dtype=types["D"])
    for c in range(CAMERAS):
        cams["K"].append(np.array(Ks[c], dtype=types["K"]))
        if c == 3:
            cams["D"].append(shared_zeros)  # the same object as camera 0's D
        elif Ds[c] is None:
            cams["D"].append(shared_zeros if c == 0 else np.zeros((5, 1), dtype=types["D"]))
        else:
            cams["D"].append(np.array(Ds[c], dtype=types["D"]).reshape(5, 1))
        if c == 1:
            # World-to-camera as the transpose of camera-to-world: Fortran order.
            r = np.array(Rs[c], dtype=types["R"]).T.copy().T
            assert r.flags.f_contiguous and not r.flags.c_contiguous
        else:
            r = np.array(Rs[c], dtype=types["R"])
        cams["R"].append(r)
        if c == 2:
            # Sliced from a 4x4 extrinsic matrix: neither C- nor Fortran-contiguous.
            e = np.eye(4, dtype=types["T"])
            e[:3, 3] = Ts[c]
            t = e[:3, 3:]
            assert not t.flags.c_contiguous and not t.flags.f_contiguous
        else:
            t = np.array(Ts[c], dtype=types["T"]).reshape(3, 1)
        cams["T"].append(t)
    return {"cams": cams, "ims": [{"ims": list(paths)} for paths in ims]}


def smpl_params(types, frame):
    p = smpl[frame]
    return {
        "poses": np.array(p["poses"], dtype=types["poses"]),
        "Rh": np.array(p["Rh"], dtype=types["rest"]),
        "Th": np.array(p["Th"], dtype=types["rest"]),
        "shapes": np.array(p["shapes"], dtype=types["rest"]),
    }


def save(path, value, how):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    if how == "save":
        np.save(path, value)
    else:
        arr = np.array(value)  # a 0-d object array, as np.save makes it
        with open(path, "wb") as f:
            np.lib.format.write_array_header_1_0(f, np.lib.format.header_data_from_array_1_0(arr))
            pickle.dump(arr, f, protocol=int(how[1:]))
    back = np.load(path, allow_pickle=True).item()
    assert set(back) == set(value), (path, back.keys())


def expect(case_dir, name, arrays):
    np.save(os.path.join(case_dir, "expected", name + ".npy"), np.stack([np.asarray(a, dtype=np.float64) for a in arrays]))


cases = []
for dtype, types in DTYPES.items():
    for how in ["save", "p2", "p3", "p4", "p5"]:
        case = f"{dtype}_{how}"
        d = os.path.join(out, case)
        os.makedirs(os.path.join(d, "expected"), exist_ok=True)
        a = annots(types)
        save(os.path.join(d, "annots.npy"), a, how)
        for key in "KDRT":
            expect(d, key, a["cams"][key])
        with open(os.path.join(d, "expected", "ims.txt"), "w") as f:
            for entry in a["ims"]:
                f.write("\t".join(entry["ims"]) + "\n")
        for frame in range(2):
            p = smpl_params(types, frame)
            save(os.path.join(d, "smpl_params", f"{frame}.npy"), p, how)
            for key, value in p.items():
                expect(d, f"smpl{frame}_{key}", [value])
        cases.append(case)

with open(os.path.join(out, "cases.txt"), "w") as f:
    f.write("\n".join(cases) + "\n")
