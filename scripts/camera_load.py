#!/usr/bin/env python3
"""Cameras on the wire under load: fake GigE Vision cameras (brokenray-fakecam) at a rate into
`brokenray serve`, all inside a network namespace of their own with only loopback (the script
runs itself again under `unshare -rn`). Prints what the service took, what it cost, how late the
results were, and how the device clocks were fitted.

    cargo build --release --features genicam -p brokenray -p brokenray-fakecam
    python3 scripts/camera_load.py [--seconds 60] [--rate 25] [--drift-ppm 30]

The built-in installation's three cameras (C1, C2 1280x1024, C3 1392x1040), Mono8, free-running,
`host_fit`; C1's fake stamps with the host's UTC, C2's and C3's count from their own start and
run `--drift-ppm` fast and slow. Frames are rendered once by `brokenray simulate` (a still scene).

Figures:
* per camera: frames received, ingested, dropped, incomplete, refused for their time, before the
  clock fit, failed; the share of ingested frames whose marker was found (from the stored
  samples against the frames ingested);
* the service's CPU over the run (user + system of the `serve` process, which holds acquisition,
  detection and ingest), in cores;
* the delay from the middle of the exposure to the result committed (the service's own median and
  99th percentile over the newest 1000 frames of each camera);
* the clock: each fake logs every frame's device stamp and the host's UTC as it made the frame
  (`--stamps`); a stored sample's time less half the exposure, less the UTC of the frame it came
  from (the nearest), is the error of its time. Reported over the run and per minute (median and
  largest magnitude), with the fitted drift against the fake's.
"""
import argparse
import bisect
import json
import os
import pathlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request

ROOT = pathlib.Path(__file__).resolve().parent.parent
BIN = ROOT / "target" / "release"
INSIDE = "BROKENRAY_CAMERA_LOAD_NETNS"
URL = "http://127.0.0.1:7878"


def get(path):
    with urllib.request.urlopen(URL + path, timeout=30) as r:
        return json.load(r)


def cpu_seconds(pid):
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--seconds", type=float, default=60)
    p.add_argument("--rate", type=float, default=25)
    p.add_argument("--drift-ppm", type=float, default=30)
    args = p.parse_args()
    if os.environ.get(INSIDE) is None:
        env = dict(os.environ, **{INSIDE: "1"})
        sys.exit(subprocess.call(["unshare", "-rn", "--", sys.executable, __file__] + sys.argv[1:], env=env))
    subprocess.check_call(["ip", "link", "set", "lo", "up"])
    for i in (2, 3, 4):
        subprocess.check_call(["ip", "addr", "add", f"127.0.0.{i}/8", "dev", "lo"])
    work = pathlib.Path(tempfile.mkdtemp(prefix="camera-load-"))
    children = []
    try:
        subprocess.check_call(
            [BIN / "brokenray", "simulate", "--scenario", "static", "--duration", "1s", "--rate", "3",
             "--emit", "frames", "--out", work / "frames"], stderr=subprocess.DEVNULL)
        clocks = {"C1": ["--clock", "utc"],
                  "C2": ["--clock", "boot", "--drift-ppm", str(args.drift_ppm)],
                  "C3": ["--clock", "boot", "--drift-ppm", str(-args.drift_ppm)]}
        text = (ROOT / "src" / "config" / "default.toml").read_text()
        text = text.replace('database = "brokenray.db"', f'database = "{work / "db.sqlite"}"')
        for i, camera in enumerate(["C1", "C2", "C3"]):
            fake = subprocess.Popen([BIN / "brokenray-fakecam", "--address", f"127.0.0.{i + 2}",
                                     "--frames", work / "frames" / camera, "--stamps", work / f"{camera}.stamps"]
                                    + clocks[camera],
                                    stdout=subprocess.PIPE)
            children.append(fake)
            assert fake.stdout.readline().strip() == b"ready"
            source = (f'{{ address = "127.0.0.{i + 2}", rate_hz = {args.rate}, exposure_us = 2000, '
                      f'timestamp = "host_fit" }}')
            text = text.replace(f'[[cameras]]\nframe = "{camera}"',
                                f'[[cameras]]\nframe = "{camera}"\nsource = {source}', 1)
        (work / "installation.toml").write_text(text)
        serve = subprocess.Popen([BIN / "brokenray", "serve", "--config", work / "installation.toml"],
                                 stderr=open(work / "serve.log", "w"))
        children.append(serve)
        for _ in range(300):
            try:
                get("/healthz")
                break
            except Exception:
                time.sleep(0.1)
        # Past the clock fit's first seconds.
        time.sleep(5)
        start_cpu, start_wall = cpu_seconds(serve.pid), time.monotonic()
        start_counts = {c["name"]: c["source"] for c in get("/api/v1/cameras")["cameras"]}
        start_ns = time.time_ns()
        minutes = []
        next_report = time.monotonic() + 60
        while time.monotonic() - start_wall < args.seconds:
            time.sleep(1)
            if time.monotonic() >= next_report:
                next_report += 60
                minutes.append({c["name"]: c["source"].get("clock_fit") for c in get("/api/v1/cameras")["cameras"]})
        cpu = (cpu_seconds(serve.pid) - start_cpu) / (time.monotonic() - start_wall)
        end = {c["name"]: c for c in get("/api/v1/cameras")["cameras"]}
        period_ns = round(1e9 / args.rate)
        print(f"{args.seconds:.0f} s at {args.rate} Hz, three cameras; serve used {cpu:.3f} cores "
              f"(acquisition, detection and ingest)")
        for camera, link in [("C1", "C1_from_B"), ("C2", "C2_from_M"), ("C3", "C3_from_G")]:
            s, s0 = end[camera]["source"], start_counts[camera]
            d = {k: s[k] - s0[k] for k in ["frames_received", "frames_ingested", "frames_dropped",
                                           "incomplete_buffers", "frames_refused_time", "frames_failed",
                                           "frames_before_clock_fit"]}
            samples = get(f"/api/v1/links/{link}/samples?limit=100000")["samples"]
            times = []
            for x in samples:
                t = x["time"]
                sec, frac = t.rstrip("Z").split(".")
                ns = int(time.mktime(time.strptime(sec, "%Y-%m-%dT%H:%M:%S")) - time.timezone) * 10**9 \
                    + int(frac.ljust(9, "0"))
                if ns >= start_ns:
                    times.append(ns)
            made = sorted(int(line.split()[1]) for line in open(work / f"{camera}.stamps") if line.strip())
            errors_ms = []
            for t in times:
                middle = t - 1_000_000
                i = bisect.bisect_left(made, middle)
                nearest = min(made[max(0, i - 1):i + 1], key=lambda m: abs(m - middle))
                errors_ms.append((middle - nearest) / 1e6)
            print(f"{camera}: received {d['frames_received']}, ingested {d['frames_ingested']}, "
                  f"dropped {d['frames_dropped']}, incomplete {d['incomplete_buffers']}, refused for their time "
                  f"{d['frames_refused_time']}, failed {d['frames_failed']}; samples stored {len(times)} "
                  f"(marker found in {len(times) / max(1, d['frames_ingested']):.3f} of the frames); delay median "
                  f"{s.get('delay_median_ms', 0):.1f} ms, p99 {s.get('delay_p99_ms', 0):.1f} ms")
            if errors_ms:
                print(f"    time error (stored less exposure middle): median {statistics.median(errors_ms):.2f} ms, "
                      f"largest {max(errors_ms, key=abs):.2f} ms; fit {s.get('clock_fit')}")
                per_minute = {}
                for t, e in zip(times, errors_ms):
                    per_minute.setdefault((t - start_ns) // 60_000_000_000, []).append(e)
                if len(per_minute) > 1:
                    print("    per minute (median/largest ms): " + ", ".join(
                        f"{statistics.median(v):.2f}/{max(v, key=abs):.2f}" for _, v in sorted(per_minute.items())))
        print(f"(C2's device clock runs {args.drift_ppm} ppm fast, C3's as much slow: the host's against "
              f"them {-args.drift_ppm:+.2f} and {args.drift_ppm:+.2f} ppm)")
        for i, m in enumerate(minutes):
            print(f"minute {i + 1}: " + "; ".join(
                f"{c} offset {f['offset_ms']:.3f} ms drift {f['drift_ppm']:.2f} ppm rms {f['residual_rms_us']:.0f} us"
                for c, f in m.items() if f))
    finally:
        for c in reversed(children):
            c.terminate()
            c.wait()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
