#!/usr/bin/env python3
"""Compares brokenray's disc detection with OpenCV's on the same rendered frames (a development
script, not a dependency of the service).

    cargo build --release
    target/release/brokenray simulate --emit frames --scenario static --duration 4s --rate 25 \
        --start 2026-11-21T10:00:00Z --out target/frames
    python3 -m venv target/cv && target/cv/bin/pip install opencv-python-headless numpy
    target/cv/bin/python scripts/detect_vs_opencv.py target/release/brokenray target/frames C1

For every frame of the camera: brokenray (`brokenray detect`, one process over all frames:
decoding, detection, identification, weighted PnP and the eccentricity correction) against
OpenCV (cv2.imread, SimpleBlobDetector, the blobs matched to the marker's points projected from
the link's nominal pose, solvePnP SQPNP + solvePnPRefineLM). Accuracy is measured against the
truth the simulator wrote: each point's distance from the projection of its disc's centre at the
true pose (px), and the pose error of each method's own solve. Speed is frames per second of
wall time, startup included for brokenray.
"""
import json
import math
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import cv2
import numpy as np


def rotation_from_euler_deg(e):
    ax, ay, az = (math.radians(v) for v in e)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rz = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def rotation_from_q(q):
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotation_error_arcsec(r_est, r_true):
    d = r_est @ r_true.T
    c = max(-1.0, min(1.0, (np.trace(d) - 1.0) / 2.0))
    return math.degrees(math.acos(c)) * 3600.0


def blob_detector():
    """OpenCV's detector of the bright discs of the rendered frames (also used by
    scripts/no_prior_vs_opencv.py, so the two comparisons run the same detector)."""
    params = cv2.SimpleBlobDetector_Params()
    params.filterByColor = True
    params.blobColor = 255
    params.minThreshold = 60
    params.maxThreshold = 200
    params.filterByArea = True
    params.minArea = 12
    params.maxArea = 40000
    params.filterByCircularity = True
    params.minCircularity = 0.7
    params.filterByInertia = False
    params.filterByConvexity = False
    return cv2.SimpleBlobDetector_create(params)


def main(binary, frames_dir, camera_name):
    frames_dir = Path(frames_dir)
    config = tomllib.loads(subprocess.run([binary, "default-config"], capture_output=True, text=True, check=True).stdout)
    camera = next(c for c in config["cameras"] if c["frame"] == camera_name)
    link = next(l for l in config["links"] if l["name"].startswith(camera_name + "_from_") and l["kind"] == "measured")
    marker = next(m for m in config["markers"] if m["frame"] == link["name"].split("_from_")[1])
    k = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1]], dtype=np.float64)
    dist = np.array(camera["distortion"], dtype=np.float64)
    points = np.array(marker["points_mm"], dtype=np.float64)
    nominal_r = rotation_from_euler_deg(link["nominal"]["euler_deg"])
    nominal_t = np.array(link["nominal"]["t_mm"], dtype=np.float64)
    truth = {json.loads(l)["time"]: json.loads(l) for l in open(frames_dir / "truth.ndjson")}
    files = sorted((frames_dir / camera_name).glob("*.png"))

    # brokenray: one process over every frame.
    t0 = time.perf_counter()
    out = subprocess.run([binary, "detect", "--camera", camera_name, *map(str, files)], capture_output=True, text=True, check=True)
    ours_s = time.perf_counter() - t0
    ours = [json.loads(l) for l in out.stdout.splitlines()]

    # OpenCV.
    detector = blob_detector()
    predicted, _ = cv2.projectPoints(points, cv2.Rodrigues(nominal_r)[0], nominal_t, k, dist)
    predicted = predicted.reshape(-1, 2)
    cv_results = []
    t0 = time.perf_counter()
    for f in files:
        image = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        blobs = np.array([kp.pt for kp in detector.detect(image)], dtype=np.float64).reshape(-1, 2)
        matched = []
        for p in predicted:
            if len(blobs) == 0:
                break
            d = np.linalg.norm(blobs - p, axis=1)
            j = int(np.argmin(d))
            if d[j] < 40:
                matched.append(blobs[j])
            else:
                matched.append(None)
        ids = [i for i, m in enumerate(matched) if m is not None]
        if len(ids) < 4:
            cv_results.append(None)
            continue
        img = np.array([matched[i] for i in ids], dtype=np.float64)
        ok, rvec, tvec = cv2.solvePnP(points[ids], img, k, dist, flags=cv2.SOLVEPNP_SQPNP)
        rvec, tvec = cv2.solvePnPRefineLM(points[ids], img, k, dist, rvec, tvec)
        cv_results.append((ids, img, rvec, tvec))
    cv_s = time.perf_counter() - t0

    def errors(time_text, ids, pixels, r, t):
        tr = truth[time_text]["links"][link["name"]]
        r_true = rotation_from_q(tr["q_wxyz"])
        t_true = np.array(tr["t_mm"])
        true_px, _ = cv2.projectPoints(points[ids], cv2.Rodrigues(r_true)[0], t_true, k, dist)
        point_err = np.linalg.norm(np.asarray(pixels) - true_px.reshape(-1, 2), axis=1)
        return point_err, rotation_error_arcsec(r, r_true), float(np.linalg.norm(t - t_true))

    rows = {"brokenray": [], "OpenCV": []}
    for o in ours:
        ids = o["ids"]
        pixels = np.array(o["points_px"])
        # The pose from brokenray's points, solved the same way as OpenCV's, so that the pose
        # error compares the detectors (the service's own weighted PnP does a little better).
        ok, rvec, tvec = cv2.solvePnP(points[ids], pixels, k, dist, flags=cv2.SOLVEPNP_SQPNP)
        rvec, tvec = cv2.solvePnPRefineLM(points[ids], pixels, k, dist, rvec, tvec)
        rows["brokenray"].append(errors(o["time"], ids, pixels, cv2.Rodrigues(rvec)[0], tvec.ravel()))
    times = [json.loads(l)["time"] for l in open(frames_dir / "truth.ndjson")]
    for time_text, r in zip(times, cv_results):
        if r is None:
            continue
        ids, img, rvec, tvec = r
        rows["OpenCV"].append(errors(time_text, ids, img, cv2.Rodrigues(rvec)[0], tvec.ravel()))

    print(f"{len(files)} frames of camera {camera_name} ({link['name']}, {len(points)} discs)")
    print(f"{'':10} {'found':>6} {'point rms px':>13} {'point max px':>13} {'rot rms arcsec':>15} {'t rms mm':>9} {'frames/s':>9}")
    for name, seconds in (("brokenray", ours_s), ("OpenCV", cv_s)):
        r = rows[name]
        if not r:
            print(f"{name:10} {0:>6}")
            continue
        pe = np.concatenate([x[0] for x in r])
        rot = math.sqrt(sum(x[1] ** 2 for x in r) / len(r))
        tr = math.sqrt(sum(x[2] ** 2 for x in r) / len(r))
        print(f"{name:10} {len(r):>6} {math.sqrt(np.mean(pe ** 2)):>13.4f} {pe.max():>13.4f} {rot:>15.2f} {tr:>9.4f} {len(files) / seconds:>9.1f}")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
