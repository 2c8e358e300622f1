#!/usr/bin/env python3
"""Calibrates cameras from real photographs of dot plates with brokenray and compares the
result with OpenCV's and with each set's published calibration (a development script: the
photographs are third-party data, read where they lie and never copied into the repository).

    cargo build --release
    python3 scripts/real_plates.py target/release/brokenray DIR

DIR holds the sets, one folder each (`industrial_calibration_10x10`, `boofcv_circles/...`).

For each set (a folder with its frames, a `plate.toml` or the plate given below, and
`opencv_baseline.json` holding what OpenCV found: its views and its calibration), it runs
`brokenray calibrate-camera --json` on every frame and prints the views the plate was found in
(brokenray's and OpenCV's), the intrinsics, and their differences from the published ones (the
source's own where it has them, else OpenCV's).
"""
import json
import subprocess
import sys
import tempfile
from pathlib import Path

# Plates the sets describe in their own words (see each set's readme).
PLATES = {
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


def main(binary, root):
    root = Path(root)
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


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(*sys.argv[1:])
