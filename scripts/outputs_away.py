#!/usr/bin/env python3
"""Load generator: the plant's outputs while their MQTT broker is away, and when it returns.

Runs `brokenray serve` on the built-in installation with three targets (G, M and C3, each from
B), fed at 25 Hz in real time by `brokenray simulate` (the ship), its three outputs on (MQTT
to a Mosquitto broker this script starts on a loopback port, Modbus/TCP, NMEA by UDP), then:

1. runs `--warm` seconds with the broker there, and reads the service's RSS;
2. stops the broker for `--away` seconds (default 600), reading the RSS every 10 s, and the
   output's state from `GET /api/v1/outputs` (with `--control` the broker stays: the same run
   with nothing away, to tell the outputs' memory from the rest of the service's);
3. starts the broker again (with nothing retained) and measures how long until a subscriber has
   every target's newest compensation (the service publishes what it kept);

and prints the figures. Everything listens on 127.0.0.1.

    python3 scripts/outputs_away.py [--bin target/release/brokenray] [--away 600] [--warm 60] [--control]
"""

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def get(base, path):
    with urllib.request.urlopen(base + path, timeout=5) as r:
        return json.load(r)


def start_broker(conf):
    p = subprocess.Popen(["mosquitto", "-c", conf], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return p


def wait_port(port, limit=10.0):
    start = time.time()
    while time.time() - start < limit:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.02)
    sys.exit(f"nothing listens on {port}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default="target/release/brokenray")
    ap.add_argument("--away", type=float, default=600.0)
    ap.add_argument("--warm", type=float, default=60.0)
    ap.add_argument("--control", action="store_true")
    args = ap.parse_args()

    tmp = tempfile.mkdtemp(prefix="brokenray-away-")
    mqtt_port, modbus_port, http_port = free_port(), free_port(), free_port()
    nmea = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    nmea.bind(("127.0.0.1", 0))
    nmea.setblocking(False)
    conf = os.path.join(tmp, "mosquitto.conf")
    with open(conf, "w") as f:
        f.write(f"listener {mqtt_port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
    text = subprocess.run([args.bin, "default-config"], capture_output=True, text=True, check=True).stdout
    text = text.replace('database = "brokenray.db"', f'database = "{tmp}/away.db"')
    text = text.replace("127.0.0.1:7878", f"127.0.0.1:{http_port}")
    text += "\n[[targets]]\nname = \"M\"\nbase = \"B\"\n\n[[targets]]\nname = \"C3\"\nbase = \"B\"\n"
    text += (
        f"\n[[outputs.mqtt]]\nurl = \"mqtt://127.0.0.1:{mqtt_port}\"\nrate_hz = 25\n"
        f"\n[[outputs.modbus]]\nlisten = \"127.0.0.1:{modbus_port}\"\n"
        f"\n[[outputs.nmea]]\nto = \"127.0.0.1:{nmea.getsockname()[1]}\"\nrate_hz = 10\n"
    )
    inst = os.path.join(tmp, "inst.toml")
    with open(inst, "w") as f:
        f.write(text)
    broker = start_broker(conf)
    wait_port(mqtt_port)
    total = args.warm + args.away + 60
    service = subprocess.Popen([args.bin, "serve", "--config", inst], cwd=tmp,
                               stdout=subprocess.DEVNULL, stderr=open(os.path.join(tmp, "serve.log"), "w"))
    wait_port(http_port, 60)
    feeder = subprocess.Popen(
        [args.bin, "simulate", "--config", inst, "--scenario", "ship", "--rate", "25",
         "--duration", f"{int(total)}s", "--to", f"http://127.0.0.1:{http_port}"],
        cwd=tmp, stdout=subprocess.DEVNULL, stderr=open(os.path.join(tmp, "simulate.log"), "w"))
    base = f"http://127.0.0.1:{http_port}"
    time.sleep(args.warm)
    before = rss_mb(service.pid)
    outputs = get(base, "/api/v1/outputs")
    sent_before = {o["kind"]: o["sent"] for o in outputs}
    print(f"after {args.warm:.0f} s with the broker: service RSS {before:.1f} MB; sent {sent_before}")

    # A reference, so that every compensation carries its deformation.
    for t in ("G", "M", "C3"):
        now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        since = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(time.time() - 5))
        req = urllib.request.Request(base + f"/api/v1/targets/{t}/reference",
                                     data=json.dumps({"from": since, "to": now}).encode(),
                                     headers={"content-type": "application/json"})
        urllib.request.urlopen(req, timeout=5).read()
    if not args.control:
        broker.terminate()
        broker.wait()
    away_start = time.time()
    peak = before
    while time.time() - away_start < args.away:
        time.sleep(10)
        peak = max(peak, rss_mb(service.pid))
        while True:
            try:
                nmea.recv(512)
            except BlockingIOError:
                break
    after = rss_mb(service.pid)
    mqtt = [o for o in get(base, "/api/v1/outputs") if o["kind"] == "mqtt"][0]
    what = "with the broker (control)" if args.control else "without the broker"
    print(f"after {args.away:.0f} s {what}: service RSS {after:.1f} MB "
          f"(peak {peak:.1f} MB, {after - before:+.1f} MB against before); "
          f"MQTT connected={mqtt['connected']} queued={mqtt['queued']} dropped={mqtt['dropped']}")
    newest = {t: get(base, f"/api/v1/targets/{t}/compensation")["time"] for t in ("G", "M", "C3")}

    if args.control:
        feeder.terminate()
        service.terminate()
        service.wait()
        broker.terminate()
        broker.wait()
        return
    broker = start_broker(conf)
    returned = time.time()
    wait_port(mqtt_port)
    sub = subprocess.Popen(
        ["mosquitto_sub", "-h", "127.0.0.1", "-p", str(mqtt_port), "-v", "-t", "brokenray/targets/+/compensation"],
        stdout=subprocess.PIPE, text=True)
    seen = {}
    for line in sub.stdout:
        topic, payload = line.split(" ", 1)
        target = topic.split("/")[2]
        if target not in seen and json.loads(payload)["time"] >= newest[target]:
            seen[target] = time.time() - returned
        if len(seen) == 3:
            break
    sub.terminate()
    print("every target's newest compensation (at least as new as when the broker returned) received "
          f"{max(seen.values()):.2f} s after the broker started again: "
          + ", ".join(f"{t} {s:.2f} s" for t, s in sorted(seen.items())))
    feeder.terminate()
    service.terminate()
    service.wait()
    broker.terminate()
    broker.wait()


if __name__ == "__main__":
    main()
