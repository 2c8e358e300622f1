#!/usr/bin/env python3
"""Compares brokenray's camera calibration with OpenCV's on the same rendered plate views (a
development script, not a dependency of the service).

    cargo build --release
    python3 -m venv target/cv && target/cv/bin/pip install opencv-python-headless numpy
    target/cv/bin/python scripts/calibrate_vs_opencv.py target/release/brokenray C1 5

For each seed: `brokenray render-plate` renders 15 views of a symmetric 7 x 9 plate of dark
discs (the grid OpenCV's `findCirclesGrid` knows) as the installation's camera sees it, with
the truth; brokenray calibrates them (`calibrate-camera --json --fix k3`), OpenCV finds the grid
(`findCirclesGrid`, symmetric, its blob detector) and calibrates (`calibrateCamera` with
`CALIB_FIX_K3`). Both are compared with the true intrinsics; the table gives the RMS of each
parameter's error over the seeds, and the mean reprojection RMS each method reports.
"""
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

PLATE = "rows = 7\ncols = 9\nspacing_mm = 15.0\ndiameter_mm = 7.5\nasymmetric = false\npolarity = \"dark\"\n"
NAMES = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"]


def truth_vector(camera):
    d = camera["distortion"]
    return np.array([camera["fx"], camera["fy"], camera["cx"], camera["cy"], d[0], d[1], d[2], d[3]])


def brokenray_calibration(binary, plate, frames):
    out = subprocess.run([binary, "calibrate-camera", "--plate", str(plate), "--fix", "k3", "--json", *map(str, frames)],
                         capture_output=True, text=True, check=True)
    body = json.loads(out.stdout)
    c = body["camera"]
    d = c["distortion"]
    return np.array([c["fx"], c["fy"], c["cx"], c["cy"], d[0], d[1], d[2], d[3]]), body["rms_px"], len(body["views"])


def opencv_calibration(frames, size):
    objp = np.zeros((63, 3), np.float32)
    objp[:, :2] = np.mgrid[0:9, 0:7].T.reshape(-1, 2) * 15.0
    obj, img = [], []
    for f in frames:
        grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        ok, centres = cv2.findCirclesGrid(grey, (9, 7), flags=cv2.CALIB_CB_SYMMETRIC_GRID)
        if ok:
            obj.append(objp)
            img.append(centres)
    if len(obj) < 3:
        return None, None, len(obj)
    rms, k, dist, _, _ = cv2.calibrateCamera(obj, img, size, None, None, flags=cv2.CALIB_FIX_K3)
    d = dist.ravel()
    return np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2], d[0], d[1], d[2], d[3]]), rms, len(obj)


def main(binary, camera_name, seeds):
    errors = {"brokenray": [], "OpenCV": []}
    rms = {"brokenray": [], "OpenCV": []}
    views = {"brokenray": 0, "OpenCV": 0}
    with tempfile.TemporaryDirectory() as tmp:
        plate = Path(tmp) / "plate.toml"
        plate.write_text(PLATE)
        for seed in range(1, int(seeds) + 1):
            out = Path(tmp) / f"seed{seed}"
            subprocess.run([binary, "render-plate", "--camera", camera_name, "--plate", str(plate), "--views", "15",
                            "--seed", str(seed), "--out", str(out)], check=True, capture_output=True)
            truth = json.loads((out / "truth.json").read_text())
            frames = sorted(out.glob("view_*.png"))
            size = (truth["camera"]["width"], truth["camera"]["height"])
            t = truth_vector(truth["camera"])
            ours, our_rms, our_views = brokenray_calibration(binary, plate, frames)
            errors["brokenray"].append(ours - t)
            rms["brokenray"].append(our_rms)
            views["brokenray"] += our_views
            cv, cv_rms, cv_views = opencv_calibration(frames, size)
            views["OpenCV"] += cv_views
            if cv is not None:
                errors["OpenCV"].append(cv - t)
                rms["OpenCV"].append(cv_rms)
    print(f"camera {camera_name}, {seeds} seeds of 15 views of a symmetric 7 x 9 plate; RMS of the error against the truth")
    print(f"{'':10} {'views':>6} " + " ".join(f"{n:>10}" for n in NAMES) + f" {'rms px':>8}")
    for name in ("brokenray", "OpenCV"):
        e = np.array(errors[name])
        if len(e) == 0:
            print(f"{name:10} {views[name]:>6} (no calibration)")
            continue
        per = np.sqrt(np.mean(e ** 2, axis=0))
        print(f"{name:10} {views[name]:>6} " + " ".join(f"{v:>10.2e}" for v in per) + f" {np.mean(rms[name]):>8.4f}")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
