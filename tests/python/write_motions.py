"""Motion files as people write them, with real numpy, for the motion loader's tests.

Usage: write_motions.py OUT_DIR

Writes OUT_DIR/<case>.npz and, beside each file the loader should accept, what it
should load as text (OUT_DIR/<case>.expected/{poses,trans,fps}.txt, '%.17g', so f64
values travel exactly and independently of the .npy reader under test). The AMASS
cases' expectations are converted here the way AMASS users do it: the -90 degree
rotation about x (scipy's Rotation for the root orientation), the first frame's
translation subtracted, the two SMPL hand joints zero.
"""

import os
import sys

import numpy as np
from scipy.spatial.transform import Rotation

out = sys.argv[1]
os.makedirs(out, exist_ok=True)
rng = np.random.default_rng(15)
F = 6


def expect(case, poses72, trans, fps):
    d = os.path.join(out, case + ".expected")
    os.makedirs(d, exist_ok=True)
    np.savetxt(os.path.join(d, "poses.txt"), poses72, fmt="%.17g")
    np.savetxt(os.path.join(d, "trans.txt"), trans, fmt="%.17g")
    np.savetxt(os.path.join(d, "fps.txt"), [fps], fmt="%.17g")


def small_poses(width, amplitude=0.6):
    # Joint rotations well inside 180 degrees that change smoothly from frame to frame,
    # as a body makes them (the AMASS file is also simulated in cloth end to end).
    t = np.arange(F)[:, None] / F
    base = rng.uniform(-amplitude, amplitude, size=(1, width))
    return base + 0.1 * amplitude * np.sin(2 * np.pi * t + rng.uniform(0, 2 * np.pi, size=(1, width)))


def amass_expected(poses, trans):
    """SMPL poses and translation of an AMASS sequence in a y-up frame."""
    body = np.zeros((F, 72))
    body[:, :66] = poses[:, :66]
    to_y_up = Rotation.from_euler("x", -90, degrees=True)
    body[:, :3] = (to_y_up * Rotation.from_rotvec(poses[:, :3])).as_rotvec()
    r = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    t = trans @ r.T
    return body, t - t[0]


# (a) numpy users' own format: a 0-d int64 fps, as np.savez(fps=30) writes it.
poses = small_poses(72)
# A root that moves as people do (a few centimetres a frame): drape refuses a root
# faster than 20 m/s.
trans = np.array([0.3, 0.9, -0.5]) + 0.03 * np.cumsum(rng.uniform(-1.0, 1.0, size=(F, 3)), axis=0)
np.savez(os.path.join(out, "smpl_0d_fps.npz"), poses=poses, trans=trans, fps=30)
expect("smpl_0d_fps", poses, trans, 30)

# The same saved from a transposed (Fortran-ordered) array: numpy writes it as such.
np.savez(os.path.join(out, "smpl_fortran.npz"), poses=np.asfortranarray(poses), trans=np.asfortranarray(trans), fps=np.array([30.0]))
expect("smpl_fortran", poses, trans, 30)

# 22 joints only (F x 66), fps of shape (1).
poses66 = small_poses(66)
np.savez(os.path.join(out, "body22.npz"), poses=poses66, trans=trans, fps=np.array([20.0]))
p = np.zeros((F, 72))
p[:, :66] = poses66
expect("body22", p, trans, 20)

# (b) AMASS (SMPL-H): 156 pose values, a 0-d mocap_framerate, betas, a text gender,
# dmpls. Standing upright in AMASS's z-up world is a root of about +90 degrees about x.
poses156 = small_poses(156, 0.15)
poses156[:, :3] = (Rotation.from_euler("x", 90, degrees=True) * Rotation.from_rotvec(small_poses(3, 0.4))).as_rotvec()
# Where in the capture room: 0.93 m up (AMASS's z), a few centimetres' drift.
trans_amass = np.array([0.4, -1.2, 0.93]) + 0.02 * np.cumsum(rng.uniform(-1, 1, size=(F, 3)), axis=0)
amass = dict(poses=poses156, trans=trans_amass, mocap_framerate=np.array(120.0), betas=rng.normal(size=16), gender=np.array("male"), dmpls=rng.normal(size=(F, 8)))
np.savez(os.path.join(out, "amass.npz"), **amass)
expect("amass", *amass_expected(poses156, trans_amass), 120)

# gender pickled as an object array (np.savez pickles object arrays), and as bytes.
np.savez(os.path.join(out, "amass_object_gender.npz"), **{**amass, "gender": np.array("female", dtype=object)})
expect("amass_object_gender", *amass_expected(poses156, trans_amass), 120)
np.savez(os.path.join(out, "amass_bytes_gender.npz"), **{**amass, "gender": np.array(b"female")})
expect("amass_bytes_gender", *amass_expected(poses156, trans_amass), 120)

# (c) compressed.
np.savez_compressed(os.path.join(out, "amass_compressed.npz"), **amass)
expect("amass_compressed", *amass_expected(poses156, trans_amass), 120)

# AMASS's SMPL-X release: 165 pose values, 'mocap_frame_rate', float32 poses.
poses165 = small_poses(165).astype(np.float32)
poses165_64 = poses165.astype(np.float64)
np.savez(os.path.join(out, "amass_smplx.npz"), poses=poses165, trans=trans_amass, mocap_frame_rate=np.array(60.0), gender=np.array("neutral"), surface_model_type=np.array("smplx"))
expect("amass_smplx", *amass_expected(poses165_64, trans_amass), 60)

# Mistakes, each to be refused in one line naming the file and the field.
np.savez(os.path.join(out, "bad_width.npz"), poses=small_poses(100), trans=trans, fps=30)
nan = poses.copy()
nan[2, 7] = np.nan
np.savez(os.path.join(out, "bad_nan.npz"), poses=nan, trans=trans, fps=30)
np.savez(os.path.join(out, "bad_no_poses.npz"), trans=trans, fps=30)
np.savez(os.path.join(out, "bad_frames.npz"), poses=poses, trans=trans[:-1], fps=30)
np.savez(os.path.join(out, "bad_no_frames.npz"), poses=np.zeros((0, 72)), trans=np.zeros((0, 3)), fps=30)
np.savez(os.path.join(out, "bad_fps.npz"), poses=poses, trans=trans, fps=0)
np.savez(os.path.join(out, "bad_no_fps.npz"), poses=poses, trans=trans)
np.savez(os.path.join(out, "bad_text_poses.npz"), poses=np.array("walk"), trans=trans, fps=30)
