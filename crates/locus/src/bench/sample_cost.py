#!/usr/bin/env python3
"""Instructions a camera sample costs locus and Mitsuba 3, counted by callgrind.

`locus bench quality` compares the two renderers by the clock, which on a
shared machine moves by tens of percent between days; instruction counts do
not. This script renders the scene twice with each renderer under
`valgrind --tool=callgrind`, on one thread, at a low and a high sample count,
and divides the difference of the two counts by the difference of the
samples rendered: loading, BVH builds and Mitsuba's kernel compilation
happen once in each run and cancel. It then splits Mitsuba's count by the
object that ran it (Embree, Mitsuba's compiled kernels, the rest), and
times a sample natively the same way (the difference of two renders'
times: locus's report, Mitsuba's timed render), so that the ratio of
times over the ratio of instructions says how much of the gap is
instructions retired per second.

Mitsuba's run reuses what `locus bench quality` leaves in its output folder
when it renders with Mitsuba (`<out>/mitsuba`: the scene as PLY files, the
spec and `render.py`), so run that once first:

    LOCUS_MITSUBA_PYTHON=/path/to/venv/bin/python locus bench quality --spp 16
    python3 crates/locus/src/bench/sample_cost.py --python /path/to/venv/bin/python
        [--locus target/release/locus] [--scene scenes/cornell-box/cornell.toml]
        [--mitsuba-dir bench-out/quality-cornell/mitsuba] [--sampler ldsampler]
        [--spp 4 16]

Valgrind has no AVX-512: under it Mitsuba and Embree run their AVX2 code,
so on a processor with AVX-512 their native count may be lower. Mitsuba's
`ldsampler` rounds sample counts up to a square power of two, so the counts
given should be such (4, 16, 64). Mitsuba's JIT-compiled kernels need
`--smc-check=all-non-file`, which this script passes. A run takes minutes.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile


def callgrind(cmd, out, cwd=None):
    """Runs `cmd` under callgrind (every thread counted into one file)
    and returns the file."""
    vg = ["valgrind", "--tool=callgrind", "--smc-check=all-non-file",
          f"--callgrind-out-file={out}"]
    r = subprocess.run(vg + cmd, cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed under valgrind ({r.returncode}):\n{r.stderr[-2000:]}")
    return out


def by_object(path):
    """Self instructions of the run by the object file they ran in
    (`???` for code compiled at run time), and the total."""
    out = subprocess.run(
        ["callgrind_annotate", "--threshold=100", "--tree=none", "--inclusive=no", path],
        capture_output=True, text=True, check=True).stdout
    objects, total = {}, 0
    for line in out.splitlines():
        m = re.match(r"^\s*([\d,]+) \([^)]*\)\s+(.*?)$", line)
        if not m:
            continue
        n = int(m.group(1).replace(",", ""))
        if "PROGRAM TOTALS" in line:
            total = n
            continue
        o = re.search(r"\[([^\]]*)\]\s*$", m.group(2))
        name = os.path.basename(o.group(1)) if o else "???"
        objects[name] = objects.get(name, 0) + n
    return objects, total


def pixels_of(spec):
    return spec["camera"]["width"] * spec["camera"]["height"]


def locus_run(a, spp, tmp, counted):
    """Renders with locus on one thread, under callgrind when `counted`;
    returns the program's instructions (or 0) and the report."""
    base = os.path.join(tmp, f"locus-{spp}-{'cg' if counted else 'native'}")
    cmd = [a.locus, "render", a.scene, "--threads", "1", "--spp", str(spp), "-o", base + ".exr"]
    total = 0
    if counted:
        total = by_object(callgrind(cmd, base + ".cg"))[1]
    else:
        subprocess.run(cmd, capture_output=True, check=True)
    with open(base + ".json") as f:
        return total, json.load(f)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--locus", default="target/release/locus")
    ap.add_argument("--scene", default="scenes/cornell-box/cornell.toml")
    ap.add_argument("--python", required=True, help="the Python with Mitsuba 3")
    ap.add_argument("--mitsuba-dir", default="bench-out/quality-cornell/mitsuba")
    ap.add_argument("--sampler", default="ldsampler")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--spp", type=int, nargs=2, default=[4, 16])
    a = ap.parse_args()
    lo, hi = a.spp
    if not hi > lo > 0:
        sys.exit("--spp: two counts, the second above the first")
    spec_path = os.path.join(a.mitsuba_dir, "spec.json")
    if not os.path.exists(spec_path):
        sys.exit(f"{spec_path} not found: run `locus bench quality` with Mitsuba first")
    with open(spec_path) as f:
        spec = json.load(f)
    tmp = tempfile.mkdtemp(prefix="sample-cost-")

    rows = []
    # locus: the whole process, every thread; its samples from its reports.
    totals, reports, native = [], [], []
    for spp in (lo, hi):
        t, r = locus_run(a, spp, tmp, counted=True)
        totals.append(t)
        reports.append(r)
        native.append(locus_run(a, spp, tmp, counted=False)[1]["times"]["render_s"])
    samples = [r["width"] * r["height"] * r["spp_rendered"] for r in reports]
    if (reports[0]["width"], reports[0]["height"]) != (spec["camera"]["width"], spec["camera"]["height"]):
        sys.exit(f"{a.scene} is not the scene exported to {a.mitsuba_dir} (its image size differs)")
    locus = (totals[1] - totals[0]) / (samples[1] - samples[0])
    locus_us = (native[1] - native[0]) / (samples[1] - samples[0]) * 1e6
    rows.append(("locus", totals, locus, locus_us))

    # Mitsuba: its script renders each count twice (once to compile, then
    # timed), so twice the samples; the native warm-up run's timed render
    # gives its time a sample.
    pixels = pixels_of(spec)
    objs, totals, seconds = [], [], []
    for spp in (lo, hi):
        s = dict(spec, spp=[spp], samplers=[a.sampler], threads=1, variant=a.variant)
        sp = os.path.join(a.mitsuba_dir, f"sample-cost-{spp}.json")
        with open(sp, "w") as f:
            json.dump(s, f)
        # Dr.Jit keeps compiled kernels in a cache on disk: a run that finds
        # it cold compiles where the other does not, and the difference
        # would take the compilation off the samples. One native run first
        # leaves both counted runs a warm cache.
        warm = os.path.join(tmp, f"warm-{spp}.json")
        subprocess.run([a.python, "render.py", os.path.basename(sp), warm],
                       cwd=a.mitsuba_dir, capture_output=True, check=True)
        with open(warm) as f:
            seconds.append(json.load(f)["runs"][0]["seconds"])
        cg = callgrind([a.python, "render.py", os.path.basename(sp),
                        os.path.join(tmp, f"mitsuba-{spp}.json")],
                       os.path.join(tmp, f"mitsuba-{spp}.cg"), cwd=a.mitsuba_dir)
        o, t = by_object(cg)
        objs.append(o)
        totals.append(t)
    samples = 2 * (hi - lo) * pixels
    mitsuba = (totals[1] - totals[0]) / samples
    parts = {k: (objs[1].get(k, 0) - objs[0].get(k, 0)) / samples
             for k in set(objs[0]) | set(objs[1])}
    mitsuba_us = (seconds[1] - seconds[0]) / ((hi - lo) * pixels) * 1e6
    rows.append((f"Mitsuba {a.variant} {a.sampler}", totals, mitsuba, mitsuba_us))

    print(f"{a.scene}: a camera sample, {lo} and {hi} spp on one thread")
    print("| renderer | instructions at the low count | at the high count | a sample | µs a sample, native |")
    print("|---|---:|---:|---:|---:|")
    for name, t, per, us in rows:
        print(f"| {name} | {t[0] / 1e6:,.1f} M | {t[1] / 1e6:,.1f} M | {per:,.0f} | {us:.2f} |")
    print(f"\nlocus over Mitsuba: instructions {locus / mitsuba:.2f}, time {locus_us / mitsuba_us:.2f}, "
          f"so instructions a second {(locus_us / mitsuba_us) / (locus / mitsuba):.2f} times fewer")
    print("\nMitsuba's per sample, by object (`???`: compiled at run time):")
    for k, v in sorted(parts.items(), key=lambda kv: -kv[1]):
        if v >= 1:
            print(f"  {v:8,.0f}  {k}")


main()
