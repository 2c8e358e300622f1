#!/usr/bin/env python3
"""Compares brokenray's PnP with OpenCV's on the same generated cases (a development script).

    cargo run --release --example pnp_cases > target/pnp_cases.ndjson
    python3 -m venv target/cv && target/cv/bin/pip install opencv-python-headless numpy
    target/cv/bin/python scripts/pnp_vs_opencv.py target/pnp_cases.ndjson

OpenCV: solvePnP with SOLVEPNP_SQPNP, then solvePnPRefineLM, on the same pixels, camera and
distortion. Prints, per case family, the mean rotation error (arc-seconds) and translation error
(mm) against the truth, side by side, and how many solves failed.
"""
import json
import math
import sys
from collections import defaultdict

import cv2
import numpy as np


def rotation_error_arcsec(r_est, r_true):
    d = np.asarray(r_est) @ np.asarray(r_true).T
    c = max(-1.0, min(1.0, (np.trace(d) - 1.0) / 2.0))
    return math.degrees(math.acos(c)) * 3600.0


def main(path):
    stats = defaultdict(lambda: {"n": 0, "ours_r": [], "ours_t": [], "cv_r": [], "cv_t": [], "ours_fail": 0, "cv_fail": 0})
    with open(path) as f:
        for line in f:
            c = json.loads(line)
            s = stats[c["case"]]
            s["n"] += 1
            cam = c["camera"]
            k = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], dtype=np.float64)
            dist = np.array(cam["distortion"], dtype=np.float64)
            obj = np.array(c["marker_mm"], dtype=np.float64)
            img = np.array(c["pixels"], dtype=np.float64)
            r_true = np.array(c["truth"]["r"])
            t_true = np.array(c["truth"]["t_mm"])
            if c["ours"] is None:
                s["ours_fail"] += 1
            else:
                s["ours_r"].append(rotation_error_arcsec(c["ours"]["r"], r_true))
                s["ours_t"].append(float(np.linalg.norm(np.array(c["ours"]["t_mm"]) - t_true)))
            ok, rvec, tvec = cv2.solvePnP(obj, img, k, dist, flags=cv2.SOLVEPNP_SQPNP)
            if not ok:
                s["cv_fail"] += 1
                continue
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, dist, rvec, tvec)
            r_cv, _ = cv2.Rodrigues(rvec)
            s["cv_r"].append(rotation_error_arcsec(r_cv, r_true))
            s["cv_t"].append(float(np.linalg.norm(tvec.ravel() - t_true)))
    print(f"OpenCV {cv2.__version__}; errors against the truth (0.1 px noise): mean and median rotation")
    print("(arc-seconds), mean translation (mm), solves off by more than 1 degree (a flipped planar")
    print("solution), refused or failed solves")
    head = f"{'rot mean':>9} {'median':>7} {'t mean':>7} {'flips':>5} {'fail':>4}"
    print(f"{'case':<10} {'n':>4} | brokenray {head} | OpenCV {head}")
    for name, s in stats.items():
        def cols(r, t, fail):
            mean = sum(r) / len(r) if r else float("nan")
            med = sorted(r)[len(r) // 2] if r else float("nan")
            tm = sum(t) / len(t) if t else float("nan")
            flips = sum(1 for v in r if v > 3600.0)
            return f"{mean:>9.1f} {med:>7.1f} {tm:>7.3f} {flips:>5} {fail:>4}"
        print(f"{name:<10} {s['n']:>4} | brokenray {cols(s['ours_r'], s['ours_t'], s['ours_fail'])} | "
              f"OpenCV {cols(s['cv_r'], s['cv_t'], s['cv_fail'])}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "target/pnp_cases.ndjson")
