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


def calibrate(binary, plate, frames):
    out = subprocess.run([binary, "calibrate-camera", "--plate", str(plate), "--json", *map(str, frames)],
                         capture_output=True, text=True)
    left_out = [line for line in out.stderr.splitlines() if ": left out: " in line]
    if out.returncode != 0:
        return None, left_out, out.stderr.strip().splitlines()[-1:]
    return json.loads(out.stdout), left_out, []


def half_splits(binary, plate, frames, splits=6, seed=47):
    """Mean z^2 of fx, fy, cx, cy between two halves of the frames, over `splits` random
    splits: for the reported sigmas and for the formal ones."""
    import random
    rng = random.Random(seed)
    reported, formal, worst = [], [], {}
    for _ in range(splits):
        order = list(frames)
        rng.shuffle(order)
        half = len(order) // 2
        a, _, _ = calibrate(binary, plate, sorted(order[:half]))
        b, _, _ = calibrate(binary, plate, sorted(order[half:]))
        if not a or not b:
            continue
        for k in NAMES:
            va, vb = a["camera"][k], b["camera"][k]
            sa, sb = a["sigma"][k], b["sigma"][k]
            ia = (a.get("cross_validation") or {}).get("inflation", 1.0)
            ib = (b.get("cross_validation") or {}).get("inflation", 1.0)
            z2 = (va - vb) ** 2 / (sa ** 2 + sb ** 2)
            reported.append(z2)
            formal.append((va - vb) ** 2 / (sa ** 2 / ia + sb ** 2 / ib))
            worst[k] = max(worst.get(k, 0.0), z2)
    mean = lambda v: sum(v) / len(v) if v else float("nan")
    return mean(reported), mean(formal), worst, len(reported) // 4


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
    root = Path(root)
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
            used = [f for f in frames if any(Path(v).name == f.name for v in ours.get("frames", []))] or frames
            rep, form, worst, n = half_splits(binary, plate, used)
            w = max(worst, key=worst.get) if worst else "-"
            print(f"  half-splits ({n}): mean z^2 {rep:.2f} with the reported sigmas, {form:.2f} with the "
                  f"formal ones; worst {w} {worst.get(w, float('nan')):.1f}")


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    main(*sys.argv[1:])
