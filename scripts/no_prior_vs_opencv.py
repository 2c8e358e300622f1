#!/usr/bin/env python3
"""OpenCV's frames per second on the no-prior frames `benches/frames_no_prior.rs` posts (a
development script, not a dependency of the service).

    OUT=target/no-prior cargo bench --bench frames_no_prior
    python3 -m venv target/cv && target/cv/bin/pip install opencv-python-headless numpy
    target/cv/bin/python scripts/no_prior_vs_opencv.py target/no-prior

For every frame, on one thread (`CV_THREADS=N` for OpenCV's pool of N, 0 for its default):
cv2.imread of the PGM file, SimpleBlobDetector over the whole frame (bright discs;
`scripts/detect_vs_opencv.py`'s detector, imported from it), the blobs matched to the marker's
points projected from the frame's TRUE pose (OpenCV is given the identities for free: it does no
search), solvePnP SQPNP then solvePnPRefineLM. Prints frames per second of wall time over the
loop (reading the files included, as the service's decoding is), how many frames it solved, and
its pose error against the truth.
"""
import json
import math
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from detect_vs_opencv import blob_detector


def rotation_error_arcsec(r_est, r_true):
    d = r_est @ r_true.T
    c = max(-1.0, min(1.0, (np.trace(d) - 1.0) / 2.0))
    return math.degrees(math.acos(c)) * 3600.0


def main(folder, rounds=3):
    folder = Path(folder)
    truth = json.loads((folder / "truth.json").read_text())
    cam = truth["camera"]
    k = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], dtype=np.float64)
    dist = np.array(cam["distortion"], dtype=np.float64)
    points = np.array(truth["points_mm"], dtype=np.float64)
    frames = truth["frames"]
    threads = int(os.environ.get("CV_THREADS", "1"))
    cv2.setNumThreads(threads if threads > 0 else -1)
    threads_said = f"{cv2.getNumThreads()} thread(s)"

    detector = blob_detector()
    # The identities, for free: each point's image at the true pose.
    predicted = []
    for f in frames:
        r = np.array(f["r"], dtype=np.float64)
        p, _ = cv2.projectPoints(points, cv2.Rodrigues(r)[0], np.array(f["t_mm"]), k, dist)
        predicted.append(p.reshape(-1, 2))

    for round_ in range(rounds):
        solved, rot_err, t_err = 0, [], []
        t0 = time.perf_counter()
        for f, pred in zip(frames, predicted):
            image = cv2.imread(str(folder / f["file"]), cv2.IMREAD_GRAYSCALE)
            blobs = np.array([kp.pt for kp in detector.detect(image)], dtype=np.float64).reshape(-1, 2)
            ids, img = [], []
            for i, p in enumerate(pred):
                if len(blobs) == 0:
                    break
                d = np.linalg.norm(blobs - p, axis=1)
                j = int(np.argmin(d))
                if d[j] < 10:
                    ids.append(i)
                    img.append(blobs[j])
            if len(ids) < 4:
                continue
            img = np.array(img, dtype=np.float64)
            ok, rvec, tvec = cv2.solvePnP(points[ids], img, k, dist, flags=cv2.SOLVEPNP_SQPNP)
            if not ok:
                continue
            rvec, tvec = cv2.solvePnPRefineLM(points[ids], img, k, dist, rvec, tvec)
            solved += 1
            rot_err.append(rotation_error_arcsec(cv2.Rodrigues(rvec)[0], np.array(f["r"])))
            t_err.append(float(np.linalg.norm(tvec.ravel() - np.array(f["t_mm"]))))
        seconds = time.perf_counter() - t0
        rms = lambda v: math.sqrt(sum(x * x for x in v) / len(v)) if v else float("nan")
        print(
            f"round {round_ + 1}: {len(frames)} frames, {solved} solved, "
            f"{len(frames) / seconds:.1f} frames/s on {threads_said}; "
            f"rotation rms {rms(rot_err):.1f} arcsec, translation rms {rms(t_err):.3f} mm"
        )


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
