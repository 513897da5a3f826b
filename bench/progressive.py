#!/usr/bin/env python3
"""Progressive renderer (paper 000) on the CPU: convergence time, frame times and the fill budget
reached, against the brute-force `mortar render` of the same input, measured in the same run.

Usage: bench/progressive.py [--runs N] [--mortar PATH] INPUT...

Every round runs each configuration once (interleaved, so that the machine's load hits all of them
alike) at 1920x1080, iso view; prints a markdown table of medians (min-max) over the rounds.
"""
import argparse, json, os, statistics as st, subprocess, tempfile, time

CONFIGS = [
    ("budget 1M", ["--progressive", "converge", "--budget", "1000000"]),
    ("budget 1M, paced 60 Hz", ["--progressive", "converge", "--budget", "1000000", "--pace"]),
    ("auto, 16.6 ms, paced", ["--progressive", "converge", "--budget", "auto", "--target-ms", "16.6", "--pace"]),
    ("auto, 33 ms, paced", ["--progressive", "converge", "--budget", "auto", "--target-ms", "33", "--pace"]),
    ("preload, budget 1M", ["--progressive", "converge", "--budget", "1000000", "--preload"]),
    ("preload, one frame of all", ["--progressive", "1", "--budget", "4294967295", "--preload"]),
    ("mortar render (brute force)", ["--backend", "cpu"]),
]


def med(v):
    v = [x for x in v if x is not None]
    if not v:
        return "-"
    m = st.median(v)
    if all(float(x).is_integer() for x in v):
        fmt = lambda x: f"{x:.0f}"
    else:
        fmt = (lambda x: f"{x:.0f}") if m >= 100 else (lambda x: f"{x:.2f}" if m < 10 else f"{x:.1f}")
    return f"{fmt(m)} ({fmt(min(v))}-{fmt(max(v))})" if len(v) > 1 else fmt(m)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--mortar", default="target/release/mortar")
    ap.add_argument("inputs", nargs="+")
    a = ap.parse_args()
    out = os.path.join(tempfile.gettempdir(), "mortar-progressive-bench.png")
    results = {name: [] for name, _ in CONFIGS}
    loads = [os.getloadavg()[0]]
    for _ in range(a.runs):
        for name, extra in CONFIGS:
            cmd = [a.mortar, "render", *a.inputs, "-o", out, "--width", "1920", "--height", "1080", "--json", *extra]
            t = time.monotonic()
            p = subprocess.run(cmd, capture_output=True, text=True, check=True)
            wall = time.monotonic() - t
            j = json.loads(p.stdout)
            j["wall_s"] = wall
            results[name].append(j)
            loads.append(os.getloadavg()[0])
    print(f"load average during the runs: {min(loads):.1f}-{max(loads):.1f}\n")
    print("| configuration | wall s | first image s | loaded s | converged s | after load s | frames (while loading) | frame ms loading | frame ms loaded | reproject / fill / prepare ms | fill budget loaded |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, _ in CONFIGS:
        rs = results[name]
        if name.startswith("mortar render"):
            print(f"| {name} | {med([j['wall_s'] for j in rs])} | {med([j['wall_s'] for j in rs])} | batch {med([j['batch_seconds'] for j in rs])} | - | raster {med([j['raster_seconds'] * 1e3 for j in rs])} ms | 1 | - | - | - | {rs[0]['points']} |")
            continue
        n = rs[0]["points"]
        during = lambda j: [f for f in j["frames"] if f["loaded"] < n]
        after = lambda j: [f for f in j["frames"] if f["loaded"] == n]
        pm = lambda j, k: st.median(f[k] for f in after(j))
        print(
            f"| {name} | {med([j['wall_s'] for j in rs])} | {med([j['frames'][0]['at_ms'] * 1e-3 for j in rs])} | {med([j['load_seconds'] for j in rs])} | {med([j['convergence_seconds'] for j in rs])} "
            f"| {med([j['convergence_seconds'] - j['load_seconds'] for j in rs])} | {med([j['convergence_frame'] for j in rs])} ({med([len(during(j)) for j in rs])}) "
            f"| {med([st.median(f['frame_ms'] for f in during(j)) if during(j) else None for j in rs])} | {med([pm(j, 'frame_ms') for j in rs])} "
            f"| {med([pm(j, 'reproject_ms') for j in rs])} / {med([pm(j, 'fill_ms') for j in rs])} / {med([pm(j, 'prepare_ms') for j in rs])} "
            f"| {med([pm(j, 'filled') for j in rs])} |"
        )
    print(f"\npoints {results[CONFIGS[0][0]][0]['points']}, visible {results[CONFIGS[0][0]][0]['pixels_covered']}")


main()
