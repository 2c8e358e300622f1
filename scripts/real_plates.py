#!/usr/bin/env python3
"""Calibrates cameras from real photographs of dot plates with brokenray and compares the
result with OpenCV's and with each set's published calibration (a development script: the
photographs are third-party data, read where they lie and never copied into the repository).

    cargo build --release --examples
    python3 scripts/real_plates.py target/release/brokenray DIR [target/release/examples/blobs]

DIR holds the sets, one folder each (`industrial_calibration_10x10`, `boofcv_circles/...`).

For each set (a folder with its frames, a `plate.toml` or the plate given below, and
`opencv_baseline.json` holding what OpenCV found: its views and its calibration), it runs
`brokenray calibrate-camera --json` on every frame and prints the views the plate was found in
(brokenray's and OpenCV's), the intrinsics, and their differences from the published ones (the
source's own where it has them, else OpenCV's).

It then checks the reported sigmas as calibration people do (mrcal's check): the views the
plate was found in are split into two halves at random (six splits, seeded), each half is
calibrated, and `z = (a - b) / sqrt(sa^2 + sb^2)` is taken for fx, fy, cx, cy; the mean z^2 is
about 1 for honest sigmas. It is printed for the sigmas brokenray reports (cross-validated)
and for the formal ones (the reported over the square root of the cross-validation's
inflation).

The same half-splits are made for OpenCV (`calibrateCameraExtended` on OpenCV's own centres
from `opencv_baseline.json`, its standard deviations) and for mrcal (`mrcal-calibrate-cameras`
on the same centres, OPENCV5 lens, the plate's warp fitted; its sigmas from the solve's
`(J^T J)^-1` scaled by the residual's variance) where they are installed (Debian's
`python3-opencv`, `mrcal` and `python3-mrcal`: run the script with `/usr/bin/python3` then);
mrcal takes regular grids only. Every set is also calibrated by brokenray with the plate kept
flat (`--plate-shape flat`) beside the default (`auto`), to show what the plate's shape moves,
and with the wider lens models (`--model rational` and `rational_prism`, k3 and k6 fixed), each
with its judgement of the residuals' structure.

With the `blobs` example as a third argument it first compares the detector's discs with
OpenCV's plate centres in every view: the centres OpenCV found that no disc of ours lies within
a pixel of, the discs that match none of them (clutter and the text on the plates), the median
distance between the matched centres, and the detection time per frame.
"""
import math
import json
import subprocess
import sys
import tempfile
from pathlib import Path

# Plates the sets describe in their own words (see each set's readme).
PLATES = {
    # 10 x 10, spacing 25.4 mm (the source's cal_data.yaml), discs half of it, the origin disc
    # twice as large.
    "industrial_calibration_10x10":
        "rows = 10\ncols = 10\nspacing_mm = 25.4\ndiameter_mm = 12.7\norigin_diameter_mm = 25.4\npolarity = \"dark\"\n",
    "boofcv_circles/Sony_DSC-HX5V_CircleRegular":
        "rows = 8\ncols = 10\nspacing_mm = 25.0\ndiameter_mm = 15.0\npolarity = \"dark\"\n",
    "boofcv_circles/Sony_DSC-HX5V_CircleAsym":
        "rows = 5\ncols = 4\nspacing_mm = 30.0\ndiameter_mm = 20.0\nasymmetric = true\npolarity = \"dark\"\n",
}
# Published calibrations (fx, fy, cx, cy): the sets' own results.
PUBLISHED = {
    "industrial_calibration_10x10": (542.324, 543.515, 320.474, 226.039),
    "boofcv_circles/Sony_DSC-HX5V_CircleAsym": (702.3105920586398, 703.3375263167515,
                                                314.85220222425215, 247.40680116242027),
}
NAMES = ("fx", "fy", "cx", "cy")


def sets(root):
    for baseline in sorted(root.rglob("opencv_baseline.json")):
        folder = baseline.parent
        name = str(folder.relative_to(root))
        frames = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        yield name, folder, frames, json.loads(baseline.read_text())


def calibrate(binary, plate, frames, shape="auto", model="brown", fix=()):
    fixed = ["--fix", ",".join(fix)] if fix else []
    out = subprocess.run([binary, "calibrate-camera", "--plate", str(plate), "--plate-shape", shape,
                          "--model", model, *fixed, "--json", *map(str, frames)],
                         capture_output=True, text=True)
    left_out = [line for line in out.stderr.splitlines() if ": left out: " in line]
    if out.returncode != 0:
        return None, left_out, out.stderr.strip().splitlines()[-1:]
    return json.loads(out.stdout), left_out, []


def half_splits(calibrate_half, frames, splits=6, seed=47):
    """Mean z^2 of fx, fy, cx, cy between two halves of the frames, over `splits` random
    splits (the same splits for every calibrator: the same seed and frames). `calibrate_half`
    maps frames to `(values, {kind: sigmas})` or None; the mean z^2 is returned per kind of
    sigma, with the worst parameter of the first kind and the number of splits used."""
    import random
    rng = random.Random(seed)
    z2, worst, used = {}, {}, 0
    for _ in range(splits):
        order = list(frames)
        rng.shuffle(order)
        half = len(order) // 2
        a = calibrate_half(sorted(order[:half]))
        b = calibrate_half(sorted(order[half:]))
        if not a or not b:
            continue
        used += 1
        (va, sa), (vb, sb) = a, b
        for kind in sa:
            for k in NAMES:
                z = (va[k] - vb[k]) ** 2 / (sa[kind][k] ** 2 + sb[kind][k] ** 2)
                z2.setdefault(kind, []).append(z)
                if kind == next(iter(sa)):
                    worst[k] = max(worst.get(k, 0.0), z)
    mean = {kind: sum(v) / len(v) for kind, v in z2.items()}
    return mean, worst, used


def ours_fn(binary, plate, shape):
    """brokenray's calibration of some frames: the reported and the formal sigmas."""
    def run(frames):
        r, _, _ = calibrate(binary, plate, frames, shape)
        if not r:
            return None
        inflation = (r.get("cross_validation") or {}).get("inflation", 1.0)
        values = {k: r["camera"][k] for k in NAMES}
        reported = {k: r["sigma"][k] for k in NAMES}
        formal = {k: r["sigma"][k] / math.sqrt(inflation) for k in NAMES}
        return values, {"reported": reported, "formal": formal}
    return run


def object_points(baseline):
    """The plate's points in OpenCV's order (row by row), in mm."""
    cols, rows = baseline["pattern_cols_rows"]
    s = baseline["spacing_mm"]
    asym = "ASYMMETRIC" in baseline["flags"]
    return [((2 * j + i % 2) * s if asym else j * s, i * s, 0.0) for i in range(rows) for j in range(cols)]


def opencv(root, baseline):
    """OpenCV's calibration of some frames from its own centres, with its standard deviations."""
    import cv2
    import numpy as np
    obj = np.array(object_points(baseline), np.float32)

    def run(frames):
        keys = [str(f.relative_to(root)) for f in frames]
        keys = [k for k in keys if k in baseline["centres_px"]]
        if len(keys) < 3:
            return None
        img = [np.array(baseline["centres_px"][k], np.float32).reshape(-1, 1, 2) for k in keys]
        _, K, _, _, _, std, _, _ = cv2.calibrateCameraExtended(
            [obj] * len(img), img, tuple(baseline["image_size"]), None, None)
        values = dict(zip(NAMES, (K[0, 0], K[1, 1], K[0, 2], K[1, 2])))
        return values, {"opencv": dict(zip(NAMES, std.ravel()[:4]))}
    return run


def mrcal_solve(root, baseline, tmp):
    """mrcal's calibration of some frames from OpenCV's centres (regular grids only): its
    intrinsics, its sigmas and its fitted warp (mm)."""
    import glob
    import os
    import numpy as np
    import mrcal
    cols, rows = baseline["pattern_cols_rows"]

    def run(frames):
        keys = [str(f.relative_to(root)) for f in frames]
        keys = [k for k in keys if k in baseline["centres_px"]]
        if len(keys) < 3:
            return None
        work = tempfile.mkdtemp(dir=tmp)
        corners = os.path.join(work, "corners.vnl")
        with open(corners, "w") as f:
            f.write("# filename x y level\n")
            for k in keys:
                for x, y in baseline["centres_px"][k]:
                    f.write(f"{root / k} {x} {y} 0\n")
        out = subprocess.run(
            ["mrcal-calibrate-cameras", "--corners-cache", corners, "--lensmodel", "LENSMODEL_OPENCV5",
             "--focal", str(baseline["full"]["fx"]), "--object-spacing", str(baseline["spacing_mm"] / 1000),
             "--object-width-n", str(cols), "--object-height-n", str(rows),
             "--imagersize", *map(str, baseline["image_size"]), "--outdir", work,
             # One glob for the one camera: the corners file holds only these frames.
             str((root / keys[0]).parent / "*")],
            capture_output=True, text=True)
        models = glob.glob(os.path.join(work, "*.cameramodel"))
        if out.returncode != 0 or not models:
            return None
        model = mrcal.cameramodel(models[0])
        inputs = model.optimization_inputs()
        b, x, J, _ = mrcal.optimizer_callback(**inputs)
        J = J.toarray()
        nmeas = mrcal.num_measurements_boards(**inputs)
        dof = max(nmeas - J.shape[1], 1)
        var = float(np.sum(x[:nmeas] ** 2)) / dof
        cov_packed = np.linalg.inv(J.T @ J) * var
        scale = np.ones(J.shape[1])
        mrcal.unpack_state(scale, **inputs)  # in place: the packed state's units
        sig = np.sqrt(np.diag(cov_packed)[:4]) * np.abs(scale[:4])
        intr = model.intrinsics()[1]
        values = dict(zip(NAMES, intr[:4]))
        warp_mm = np.array(inputs["calobject_warp"]) * 1000 if inputs.get("calobject_warp") is not None else None
        return values, {"mrcal": dict(zip(NAMES, sig))}, warp_mm, float(np.sqrt(np.mean(x[:nmeas] ** 2)) * math.sqrt(2))
    return run


def compare_blobs(blobs, root):
    for name, folder, frames, baseline in sets(root):
        centres = baseline["centres_px"]
        files = [str(root / k) for k in centres]
        out = subprocess.run([blobs, *files], capture_output=True, text=True, check=True)
        missed, extra, offsets, times = 0, 0, [], []
        for line, (k, cs) in zip(out.stdout.splitlines(), centres.items()):
            r = json.loads(line)
            ours = [b["c"] for b in r["blobs"]]
            times.append(r["ms"])
            matched = 0
            for c in cs:
                d = min((math.hypot(b[0] - c[0], b[1] - c[1]) for b in ours), default=99.0)
                if d > 1.0:
                    missed += 1
                    print(f"    {Path(k).name}: OpenCV's centre {c[0]:.1f}, {c[1]:.1f} has no disc of ours within 1 px")
                else:
                    matched += 1
                    offsets.append(d)
            extra += len(ours) - matched
        offsets.sort()
        median = offsets[len(offsets) // 2] if offsets else float("nan")
        print(f"{name}: OpenCV's centres without a disc of ours {missed} of {sum(map(len, centres.values()))}, "
              f"other discs {extra}, median distance {median:.4f} px, detection {sum(times) / len(times):.1f} ms a frame")


def main(binary, root, blobs=None):
    root = Path(root).resolve()
    if blobs:
        compare_blobs(blobs, root)
    with tempfile.TemporaryDirectory() as tmp:
        for name, folder, frames, baseline in sets(root):
            plate = folder / "plate.toml"
            if name in PLATES:
                plate = Path(tmp) / (name.replace("/", "_") + ".toml")
                plate.write_text(PLATES[name])
            ours, left_out, error = calibrate(binary, plate, frames)
            cv = baseline.get("full", {})
            cv_found = len(baseline.get("used_views", [])) or len(baseline.get("views", []))
            reference = PUBLISHED.get(name)
            source = "published"
            if reference is None:
                reference = tuple(cv.get(k) for k in NAMES)
                source = "OpenCV's"
            print(f"\n{name}: {len(frames)} frames")
            found = len(ours["views"]) if ours else 0
            print(f"  plate found: brokenray {found}, OpenCV {cv_found}")
            for line in left_out:
                print(f"    {line.split('/')[-1]}")
            for line in error:
                print(f"    {line}")
            if not ours:
                continue
            c = ours["camera"]
            values = (c["fx"], c["fy"], c["cx"], c["cy"])
            sigmas = tuple(ours["sigma"][k] for k in NAMES)
            print(f"  RMS {ours['rms_px']:.4f} px (OpenCV {cv.get('rms_px', float('nan')):.4f})")
            for k, v, s, r in zip(NAMES, values, sigmas, reference):
                rel = "" if k in ("cx", "cy") else f" ({100 * (v - r) / r:+.3f} %)"
                print(f"  {k}: {v:10.3f} +- {s:.3f}  {source} {r:10.3f}  difference {v - r:+.3f} px{rel}")
            for w in ours.get("warnings", []):
                print(f"  warning: {w['message']}")
            check = ours.get("cross_validation")
            if check:
                print(f"  {check['message']}")
            print(f"  {ours['plate_message']}")
            if ours.get("residual_message"):
                print(f"  {ours['residual_message']}")
            # The wider lens models (their radial factor's third terms fixed: with them free a
            # second-degree ratio is not determined).
            for model in ("rational", "rational_prism"):
                wide, _, refusal = calibrate(binary, plate, frames, "auto", model, ("k3", "k6"))
                if not wide:
                    print(f"  {model} (k3, k6 fixed): refused: {' '.join(refusal)}")
                    continue
                print(f"  {model} (k3, k6 fixed): " + ", ".join(
                    f"{k} {wide['camera'][k]:.3f} +- {wide['sigma'][k]:.3f}" for k in NAMES)
                    + f"; RMS {wide['rms_px']:.4f} px; {wide['plate_shape']} plate")
                if wide.get("residual_message"):
                    print(f"    {wide['residual_message']}")
            flat, _, _ = calibrate(binary, plate, frames, "flat")
            if flat:
                print("  with the plate kept flat: " + ", ".join(
                    f"{k} {flat['camera'][k]:.3f} +- {flat['sigma'][k]:.3f}" for k in NAMES))
            peers = []
            try:
                peers.append(("OpenCV", opencv(root, baseline)))
            except ImportError:
                print("  OpenCV: not installed (python3-opencv), left out")
            if "ASYMMETRIC" not in baseline["flags"]:
                try:
                    solve = mrcal_solve(root, baseline, tmp)
                    whole = solve(frames)
                    if whole:
                        values, sig, warp, rms = whole
                        print("  mrcal (OpenCV's centres, OPENCV5, warp fitted): " + ", ".join(
                            f"{k} {values[k]:.3f} +- {sig['mrcal'][k]:.3f}" for k in NAMES)
                            + f"; warp {warp[0]:+.3f}, {warp[1]:+.3f} mm; RMS {rms:.4f} px")
                    peers.append(("mrcal", lambda f, solve=solve: (lambda r: r and r[:2])(solve(f))))
                except ImportError:
                    print("  mrcal: not installed (mrcal, python3-mrcal), left out")
            print("  half-splits, mean z^2 of fx, fy, cx, cy (honest about 1; target 0.25 to 2):")
            rows = [("brokenray", ours_run) for ours_run in [ours_fn(binary, plate, "auto")]]
            rows += [("brokenray, plate flat", ours_fn(binary, plate, "flat"))] + peers
            for label, run in rows:
                mean, worst, n = half_splits(run, frames)
                w = max(worst, key=worst.get) if worst else "-"
                kinds = ", ".join(f"{v:.2f} ({k})" for k, v in mean.items())
                print(f"    {label:<22} {kinds}; worst {w} {worst.get(w, float('nan')):.1f}; {n} splits")


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    main(*sys.argv[1:])
