#!/usr/bin/env python3
"""Reference conversion of a Qualisys .qca.txt calibration by Pose2Sim's own code.

drape's Rust reader of Qualisys and Pose2Sim calibrations is tested against what the
real tool produces: this runs Pose2Sim 0.10.49's calib_qca_fun (Pose2Sim/calibration.py
from the wheel scripts/pose2sim-footage.sh fetches; not reimplemented here) on
Demo_SinglePerson's Calib.qca.txt with binning_factor=1 (the demo's Config.toml), and
writes, into OUT_DIR (default tests/fixtures/pose2sim):

  Calib_qualisys.toml  written by Pose2Sim's own toml_write, exactly as its
                       `calibration` step names and writes it (the format Sports2D reads);
  Calib_qualisys.json  the same per camera, plus the rotation as a 3x3 matrix.

Pose2Sim's convention (both files): x_cam = R @ X_world + t, world to camera, OpenCV
camera axes (x right, y down, z forward); t in METRES (the .qca's mm / 1000); rotation a
Rodrigues vector; K in pixels of the fov_video image; distortions [k1, k2, p1, p2] in
OpenCV's order, which Pose2Sim takes as the .qca's values / 64.

Pose2Sim/calibration.py imports Pose2Sim.common, which imports matplotlib, pandas,
scipy, opencv, rtoml, lxml, c3d and anytree at module level; all of them install from
PyPI, so nothing is stubbed: run with no venv active and this script makes
target/qca-venv (once, pinned, about 45 s and 590 MB) and re-runs itself in it.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
VENV = ROOT / "target" / "qca-venv"
REQUIREMENTS = ("numpy==2.4.6 opencv-python-headless==5.0.0.93 lxml==6.1.3 rtoml==0.14.0 "
                "matplotlib==3.11.2 pandas==3.1.1 scipy==1.17.1 c3d==0.6.0 anytree==2.13.0 "
                "contourpy==1.3.3 cycler==0.12.1 fonttools==4.68.0 kiwisolver==1.5.1 "
                "packaging==26.4 pillow==13.0.0 pyparsing==3.3.3 python-dateutil==4.0.0 "
                "tzdata==2026.6")


def ensure_venv():
    """Re-execute inside target/qca-venv, making it first when its stamp differs."""
    py = VENV / "bin" / "python"
    if Path(sys.prefix).resolve() == VENV.resolve():
        return
    stamp = VENV / ".drape-stamp"
    if not (stamp.is_file() and stamp.read_text().strip() == REQUIREMENTS and py.exists()):
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(VENV)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check",
                        "--no-cache-dir", "--no-deps", *REQUIREMENTS.split()],
                       check=True, stdout=sys.stderr)
        stamp.write_text(REQUIREMENTS + "\n")
    os.execv(str(py), [str(py), __file__, *sys.argv[1:]])


def main():
    ensure_venv()
    out_dir = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "tests" / "fixtures" / "pose2sim"
    footage = subprocess.run([str(ROOT / "scripts" / "pose2sim-footage.sh")], check=True,
                             capture_output=True, text=True).stdout.strip().splitlines()[-1]
    # The extracted root holds Pose2Sim/ and its dist-info (its modules call
    # importlib.metadata.version('pose2sim') at import).
    sys.path.insert(0, footage)
    import cv2
    import numpy as np
    from Pose2Sim.calibration import calib_qca_fun, toml_write

    qca = Path(footage) / "Pose2Sim" / "Demo_SinglePerson" / "calibration" / "Calib.qca.txt"
    ret, C, S, D, K, R, T = calib_qca_fun(str(qca), binning_factor=1)
    out_dir.mkdir(parents=True, exist_ok=True)
    toml_write(str(out_dir / "Calib_qualisys.toml"), C, S, D, K, R, T)

    cameras = []
    for c in range(len(C)):
        cameras.append({
            "name": C[c],
            "size": [float(v) for v in S[c]],
            "K": np.asarray(K[c], float).tolist(),
            "distortions": [float(v) for v in D[c]],
            "rotation_rodrigues": [float(v) for v in R[c]],
            "rotation_matrix": cv2.Rodrigues(np.asarray(R[c], float))[0].tolist(),
            "translation_m": [float(v) for v in T[c]],
            "avg_residual": float(ret[c]),
        })
    doc = {
        "source": "pose2sim 0.10.49 Pose2Sim/Demo_SinglePerson/calibration/Calib.qca.txt",
        "converter": "Pose2Sim.calibration.calib_qca_fun(path, binning_factor=1)",
        "convention": "x_cam = R @ X_world + t (world to camera, OpenCV axes: x right, y down, "
                      "z forward); t in metres; K in pixels; distortions [k1, k2, p1, p2] (OpenCV)",
        "cameras": cameras,
    }
    with open(out_dir / "Calib_qualisys.json", "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")
    print(f"qca-reference: wrote {out_dir}/Calib_qualisys.toml and .json", file=sys.stderr)


if __name__ == "__main__":
    main()
