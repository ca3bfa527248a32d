#!/usr/bin/env python3
"""Where the farm's extra time goes on the clock, sampled by perf.

`forward_cost.py` counts instructions, which do not show a load waiting on
memory or a thread woken for a packet. This script renders a scene once on
one machine and once on the embedded farm (`--workers 2 --fetch forward`
by default), each under `perf record -e task-clock`, and prints the
samples of each part of the work (functions grouped by name, as below),
whole process, with the farm's extra over one machine. It needs `perf`.

    python3 crates/locus/src/bench/forward_profile.py [--locus target/release/locus]
        [--scene scenes/generated/room.toml] [--width 320] [--height 240] [--spp 16]
        [--workers 2] [--fetch forward] [--freq 2000] [--out bench-out/forward-profile]
"""

import argparse
import os
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from forward_cost import small_scene  # noqa: E402

# Parts, in order: a function counts towards the first whose patterns its
# name contains.
PARTS = [
    ("BVH queries (`closest`, `occluded`)", ["Accel::closest", "Accel::occluded"]),
    ("routing: `trace_local`, the walk, `leaf_at`, the worker's tracer",
     ["trace_local", "walk_node", "leaf_at", "ItemTracer", "WholeScene"]),
    ("operating system (wake-ups, sockets, page faults)", ["[k]"]),
    ("slots: `open_chain`, `answer`", ["Slots::"]),
    ("encoding, decoding and copying ray items",
     ["Packet::", "Received::decode", "memmove", "Outbox", "Sends"]),
    ("batch and kernel glue (`trace_batch`, `Kernel::process`, `eval_hit`)",
     ["trace_batch", "Kernel::process", "Kernel::eval_hit", "pixel_mean"]),
    ("the engine's turn (`input`, `apply`, `route`, `originate`)",
     ["Engine::", "engine::effects"]),
    ("malloc and free", ["malloc", "free", "realloc", "_int_"]),
]
REST = "the rest (setup, shading)"


def samples(perf_data):
    """Samples by symbol (`[k] name` for the kernel's)."""
    out = subprocess.run(
        ["perf", "report", "-i", perf_data, "--no-children", "--sort", "sym",
         "-F", "sample,sym", "--stdio"],
        capture_output=True, text=True, check=True).stdout
    by = {}
    for line in out.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        n, _, sym = line.strip().partition(" ")
        if n.isdigit():
            by[sym.strip()] = by.get(sym.strip(), 0) + int(n)
    return by


def grouped(by):
    parts = {name: 0 for name, _ in PARTS}
    parts[REST] = 0
    for sym, n in by.items():
        name = next((p for p, pats in PARTS if any(x in sym for x in pats)), REST)
        parts[name] += n
    return parts


def record(args, out, extra):
    data = os.path.join(args.out, out + ".perf")
    subprocess.run(
        ["perf", "record", "-q", "-F", str(args.freq), "-e", "task-clock", "-o", data,
         args.locus, "render", os.path.join(args.out, "scene.toml"),
         "-o", os.path.join(args.out, out + ".exr")] + extra,
        check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return grouped(samples(data))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--locus", default="target/release/locus")
    ap.add_argument("--scene", default="scenes/generated/room.toml")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--fetch", default="forward")
    ap.add_argument("--freq", type=int, default=2000)
    ap.add_argument("--out", default="bench-out/forward-profile")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    small_scene(args.scene, os.path.join(args.out, "scene.toml"),
                args.width, args.height, args.spp)
    one = record(args, "one", [])
    farm = record(args, "farm", ["--workers", str(args.workers), "--fetch", args.fetch])
    print(f"| part | one machine | farm, {args.workers} workers, {args.fetch} | extra |")
    print("|---|---:|---:|---:|")
    for name in list(one):
        print(f"| {name} | {one[name]:,} | {farm[name]:,} | {farm[name] - one[name]:+,} |")
    t1, tf = sum(one.values()), sum(farm.values())
    print(f"| total | {t1:,} | {tf:,} | {tf - t1:+,} |")
    same = subprocess.run(
        [args.locus, "diff", "--exact", os.path.join(args.out, "farm.exr"),
         os.path.join(args.out, "one.exr")], capture_output=True, text=True)
    print("farm image bit-identical to one machine's:",
          "yes" if same.returncode == 0 else "NO\n" + same.stdout + same.stderr)


if __name__ == "__main__":
    main()
