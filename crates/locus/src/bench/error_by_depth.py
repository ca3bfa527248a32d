#!/usr/bin/env python3
"""Where an image's error comes from, bounce by bounce (stop 80).

Renders SCENE with paths cut at each of --depths (`locus render --max-depth
D`, D = 1 is direct light alone) with seeds 1..--seeds at --spp, and a
converged render of the full depth (--reference-spp, seed 99, kept under
--out and reused). For each depth it prints the image's mean (the light
paths of that many vertices carry), the relMSE those renders carry,
measured as the variance of a pixel across the seeds over the full
reference's (ref^2 + 1e-2), pbrt's relMSE term, averaged over pixels and
channels, and the median of the renders' times (their reports'
`render_s`). Shares are of the deepest depth given, which should be the
scene's own. The rows' differences say how much of the light, and how
much of the error, each further bounce brings; one depth run against
builds that differ (--locus, each with its own --out, since renders are
reused by name) compares their error and time, as stop 80 compared
Russian roulette's start.

    python3 crates/locus/src/bench/error_by_depth.py [--locus target/release/locus]
        [--scene scenes/cornell-box/cornell.toml] [--spp 64] [--seeds 8]
        [--depths 1 2 3 4 8] [--reference-spp 2048] [--reference REF.exr]
        [--threads 2] [--out bench-out/error-by-depth]

Needs numpy and OpenEXR (pip install numpy OpenEXR).
"""

import argparse
import json
import os
import subprocess
import sys

import numpy as np
import OpenEXR


def load(path):
    ch = OpenEXR.File(path).parts[0].channels
    if "RGB" in ch:
        return np.asarray(ch["RGB"].pixels, dtype=np.float64)
    return np.stack([np.asarray(ch[c].pixels, dtype=np.float64) for c in "RGB"], -1)


def render(a, out, spp, seed, depth=None):
    if os.path.exists(out):
        return
    cmd = [a.locus, "render", a.scene, "--spp", str(spp), "--seed", str(seed),
           "--threads", str(a.threads), "-o", out]
    if depth is not None:
        cmd += ["--max-depth", str(depth)]
    r = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{r.stderr}")


def render_s(exr):
    """The render time the report beside `exr` gives."""
    with open(os.path.splitext(exr)[0] + ".json") as f:
        return json.load(f)["times"]["render_s"]


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--locus", default="target/release/locus")
    p.add_argument("--scene", default="scenes/cornell-box/cornell.toml")
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--depths", type=int, nargs="+", default=[1, 2, 3, 4, 8])
    p.add_argument("--reference-spp", type=int, default=2048)
    p.add_argument("--reference", help="a converged render to use instead of rendering one "
                   "(builds compared against each other then share it)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default="bench-out/error-by-depth")
    a = p.parse_args()
    if a.seeds < 2:
        sys.exit("--seeds must be at least 2: the error is the spread across seeds")
    os.makedirs(a.out, exist_ok=True)
    name = os.path.splitext(os.path.basename(a.scene))[0]
    ref_path = a.reference or os.path.join(a.out, f"{name}_ref{a.reference_spp}.exr")
    if not a.reference:
        render(a, ref_path, a.reference_spp, 99)
    elif not os.path.exists(ref_path):
        sys.exit(f"--reference {ref_path}: no such file")
    ref = load(ref_path)
    den = ref ** 2 + 1e-2
    print(f"{a.scene}, {a.spp} spp, {a.seeds} seeds; reference {ref_path}, "
          f"mean {ref.mean():.5f}")
    print("| max depth | image mean | share of the light | relMSE (seeds' spread) "
          "| share of the error | render s (median) | seconds x relMSE |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    rows = []
    for d in sorted(set(a.depths)):
        imgs, times = [], []
        for s in range(1, a.seeds + 1):
            path = os.path.join(a.out, f"{name}_d{d}_spp{a.spp}_s{s}.exr")
            render(a, path, a.spp, s, d)
            imgs.append(load(path))
            times.append(render_s(path))
        imgs = np.stack(imgs)
        rel = (imgs.var(0, ddof=1) / den).mean()
        rows.append((d, imgs.mean(), rel, float(np.median(times))))
    full_mean, full_rel = rows[-1][1], rows[-1][2]
    for d, m, rel, t in rows:
        print(f"| {d} | {m:.5f} | {m / full_mean:.3f} | {rel:.3e} | {rel / full_rel:.3f} "
              f"| {t:.3f} | {t * rel:.3e} |")


if __name__ == "__main__":
    main()
