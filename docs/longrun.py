#!/usr/bin/env python3
"""The service over many jobs in a row (issue 19's benchmark, not a test).

    python3 docs/longrun.py JOBS [--scene scenes/level.gltf] [--query Q] [-- serve options...]
    e.g. python3 docs/longrun.py 300 -- --resident-gib 0.25

Starts `radiosity serve` (the release build) with a fresh data directory and posts the scene
JOBS times, one after the other. Meanwhile it samples the server's resident memory and what
`/healthz` reports every half second, and times GETs of finished timelines throughout: a
status, a frame (binary) and, now and then, a preview (which may trace a dropped timeline
again). Writes docs/longrun.json and plots docs/longrun.png (with matplotlib, if present;
Debian's python3-matplotlib for /usr/bin/python3), or --out PREFIX's.
"""

import argparse
import json
import os
import random
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def request(url, data=None, content_type=None, accept=None):
    req = urllib.request.Request(url, data=data, method="POST" if data is not None else "GET")
    if content_type:
        req.add_header("content-type", content_type)
    if accept:
        req.add_header("accept", accept)
    with urllib.request.urlopen(req, timeout=600) as r:
        return r.read()


def resident(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("jobs", type=int)
    ap.add_argument("--scene", default="scenes/level.gltf")
    ap.add_argument("--query", default="fps=12")
    ap.add_argument("--out", default="docs/longrun", help="writes OUT.json and OUT.png")
    argv = sys.argv[1:]
    serve = argv[argv.index("--") + 1:] if "--" in argv else []
    args = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    args.serve = serve
    binary = os.path.join(ROOT, "target/release/radiosity")
    data = tempfile.mkdtemp(prefix="radiosity-longrun-")
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    log = open(data + ".log", "w")
    server = subprocess.Popen(
        [binary, "serve", "--addr", f"127.0.0.1:{port}", "--data-dir", data, *args.serve],
        stdout=log, stderr=log)
    try:
        while True:
            try:
                request(base + "/healthz")
                break
            except OSError:
                time.sleep(0.1)
        scene = open(os.path.join(ROOT, args.scene), "rb").read()
        kind = "model/gltf-binary" if args.scene.endswith(".glb") else "model/gltf+json"
        start = time.monotonic()
        finished = []
        samples, latencies = [], []
        stop = threading.Event()

        def sample():
            while not stop.is_set():
                h = json.loads(request(base + "/healthz"))
                samples.append({
                    "t": time.monotonic() - start,
                    "resident": resident(server.pid),
                    "traced": h["memory"]["traced_bytes"],
                    "solved": h["memory"]["solved_bytes"],
                    "timelines": h["timelines"]["total"],
                    "traced_in_memory": h["timelines"]["traced_in_memory"],
                    "data": h["data_dir_bytes"],
                })
                time.sleep(0.5)

        def get():
            n = 0
            while not stop.is_set():
                if not finished:
                    time.sleep(0.05)
                    continue
                tid, frames = random.choice(finished)
                f = random.randrange(frames)
                kinds = [("status", f"/v1/timelines/{tid}", None),
                         ("frame", f"/v1/timelines/{tid}/frames/{f}", "application/octet-stream")]
                if n % 20 == 0:
                    kinds.append(("preview", f"/v1/timelines/{tid}/frames/{f}/preview.png", None))
                for what, path, accept in kinds:
                    t0 = time.monotonic()
                    request(base + path, accept=accept)
                    latencies.append({"t": t0 - start, "what": what,
                                      "seconds": time.monotonic() - t0})
                n += 1
                time.sleep(0.05)

        threads = [threading.Thread(target=sample), threading.Thread(target=get)]
        for t in threads:
            t.start()
        job_seconds = []
        for i in range(args.jobs):
            t0 = time.monotonic()
            body = json.loads(request(f"{base}/v1/timelines?{args.query}&seed={i + 1}",
                                      data=scene, content_type=kind))
            tid = body["id"]
            while True:
                s = json.loads(request(f"{base}/v1/timelines/{tid}"))
                if s["status"] in ("done", "failed", "cancelled"):
                    break
                time.sleep(0.1)
            assert s["status"] == "done", s
            job_seconds.append(time.monotonic() - t0)
            finished.append((tid, s["frames"]))
            if (i + 1) % 10 == 0:
                last = samples[-1] if samples else {}
                print(f"job {i + 1}: {job_seconds[-1]:.2f} s, resident "
                      f"{last.get('resident', 0) >> 20} MiB", flush=True)
        time.sleep(1)
        stop.set()
        for t in threads:
            t.join()
        data_bytes = sum(os.path.getsize(os.path.join(d, f))
                         for d, _, fs in os.walk(data) for f in fs)
    finally:
        server.kill()
        server.wait()
        log.close()
        shutil.rmtree(data, ignore_errors=True)
        os.remove(data + ".log")

    def percentile(what, p):
        xs = sorted(x["seconds"] for x in latencies if x["what"] == what)
        return xs[min(len(xs) - 1, int(p / 100 * len(xs)))] if xs else None

    summary = {
        "jobs": args.jobs,
        "scene": args.scene,
        "query": args.query,
        "serve": args.serve,
        "job_seconds_median": sorted(job_seconds)[len(job_seconds) // 2],
        "resident_mib_max": max(s["resident"] for s in samples) / 2**20,
        "resident_mib_after_first_tenth": max(
            (s["resident"] for s in samples if s["timelines"] > args.jobs // 10), default=0)
        / 2**20,
        "data_bytes_per_timeline": data_bytes / args.jobs,
        "latency_ms": {
            what: {"count": sum(1 for x in latencies if x["what"] == what),
                   "p50": 1e3 * percentile(what, 50), "p95": 1e3 * percentile(what, 95)}
            for what in ("status", "frame", "preview")
            if percentile(what, 50) is not None
        },
    }
    print(json.dumps(summary, indent=2))
    with open(os.path.join(ROOT, args.out + ".json"), "w") as f:
        json.dump({"summary": summary}, f, indent=2)
    plot(summary, samples, latencies, args.out + ".png")


def plot(summary, samples, latencies, out):
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("no matplotlib: no plot", file=sys.stderr)
        return
    fig, (a, b) = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    t = [s["t"] for s in samples]
    a.plot(t, [s["resident"] / 2**20 for s in samples], label="resident")
    a.plot(t, [(s["traced"] + s["solved"]) / 2**20 for s in samples],
           label="traced state + solved frames in memory")
    a.plot(t, [s["data"] / 2**20 for s in samples], label="data directory")
    a.set_ylabel("MiB")
    a.legend(loc="upper left")
    a.set_title(f"{summary['jobs']} jobs of {summary['scene']} ({summary['query']}) in a row, "
                f"serve {' '.join(summary['serve'])}")
    for what, colour in (("status", "C0"), ("frame", "C1"), ("preview", "C2")):
        xs = [x for x in latencies if x["what"] == what]
        b.scatter([x["t"] for x in xs], [1e3 * x["seconds"] for x in xs], s=3, c=colour,
                  label=what)
    b.set_yscale("log")
    b.set_ylabel("GET latency, ms")
    b.set_xlabel("seconds")
    b.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(os.path.join(ROOT, out), dpi=90)


if __name__ == "__main__":
    main()
