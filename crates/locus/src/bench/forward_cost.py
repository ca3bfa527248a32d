#!/usr/bin/env python3
"""Instructions a forwarded query costs the farm, counted by callgrind.

Wall and CPU times on a shared machine vary by 10-30% between runs, which
is as large as the differences that matter here; instruction counts do
not. This script renders a small version of a scene three ways, each under
`valgrind --tool=callgrind`:

  - one machine (`locus render --threads 2`), counting the render's
    instructions (`locus_core::passes::pixel_mean`, inclusive);
  - a farm of a scheduler and `--workers` (two) `locus worker --threads 1` processes
    (the workers under callgrind, one file per thread; the scheduler
    natively, with a worker timeout long enough for valgrind's pace),
    counting each worker's render phase thread by thread: its engine
    (`locus_worker::engine::turns::turns`), its tracing pool's batches where it
    has a pool (`--threads` above 1), and its async runtime's worker
    threads (sockets, frames, packets decoded and encoded, control; see
    `render_by_thread`);

and prints the farm's instructions above one machine's per forwarded query,
with the farm image checked bit for bit against one machine's. It needs
valgrind and callgrind_annotate on the PATH.

    python3 crates/locus/src/bench/forward_cost.py [--locus target/release/locus]
        [--scene scenes/generated/room.toml] [--width 96] [--height 72] [--spp 4]
        [--fetch forward] [--workers 2] [--cost sampled|analytic]
        [--partitioner region-growing|morton] [--shared-percent 10] [--threads 1] [--per-thread]
        [--self-costs N]
        [--out bench-out/forward-cost]

LOCUS_CALLGRIND_ARGS adds options to every valgrind call (for instance
`--dump-instr=yes`, to see a function's cost instruction by instruction).
"""

import argparse
import functools
import glob
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time


def inclusive(path):
    """Inclusive instruction counts by function, and the program total, of
    callgrind's per-thread files `path-NN`, summed (every function counted
    here runs on one thread at a time)."""
    costs, total = {}, 0
    for part in sorted(glob.glob(path + "-*")):
        c, t = inclusive_one(part)
        total += t
        for fn, n in c.items():
            costs[fn] = costs.get(fn, 0) + n
    return costs, total


# A tracing pool thread's share of the render, and the loop of the async
# runtime's worker threads.
TRACE_BATCH = "locus_worker::engine::kernel::trace_batch"
# A tile traced whole, by a worker that holds every leaf.
TRACE_TILE = "locus_worker::engine::kernel::trace_tile"
RUNTIME_WORKER = "tokio::runtime::scheduler::multi_thread::worker::run"
SETUP_DECODE = ("locus_protocol::control::_::<impl serde_core::de::Deserialize "
                "for locus_protocol::control::SchedulerToWorker>::deserialize")

# What a worker's engine thread spends, printed by `--per-thread`.
ENGINE_PARTS = [
    "locus_worker::engine::turns::turns",
    "locus_worker::engine::state::Engine::apply",
    "locus_worker::engine::state::Engine::input",
    "locus_worker::engine::state::Engine::route",
    "locus_worker::engine::slots::Slots::answer",
    "locus_worker::engine::slots::Slots::open_chain",
    "locus_worker::engine::state::Engine::effects",
    "locus_worker::engine::outbox::Outbox::push",
    "locus_protocol::packet::Packet::push",
]


def render_by_thread(path):
    """A worker's render phase from its per-thread files `path-NN`, thread
    by thread: the engine's thread counts its loop (`turns`, with whatever
    it traces itself); a tracing pool thread the batches and whole tiles it
    traced (`trace_batch`, `trace_tile`, inclusive: not the parts of the
    region's BVH build it stole before the render); the async runtime's
    worker threads their totals (peer sockets, frames, packets decoded, the link writers'
    encoding, control messages; tokio runs its workers on blocking-pool
    threads, so they are told by the scheduler's loop, `worker::run`), less
    the job's setup message where one of them decoded it. Nothing else
    counts: the main thread reads the setup message and builds the job
    from it (and then only waits on control messages), and the other
    blocking-pool threads build the region's BVH parts. Returns (engine,
    pool, runtime, setup), `runtime` before `setup` is taken off it."""
    engine = pool = runtime = setup = 0
    for part in sorted(glob.glob(path + "-*")):
        costs, total = inclusive_one(part)
        turns = costs.get(ENGINE_PARTS[0], 0)
        traced = costs.get(TRACE_BATCH, 0) + costs.get(TRACE_TILE, 0)
        if turns:
            engine += turns
        elif traced:
            pool += traced
        elif costs.get(RUNTIME_WORKER, 0):
            runtime += total
            setup += costs.get(SETUP_DECODE, 0)
    return engine, pool, runtime, setup


def engine_thread(path):
    """The per-thread file of worker file `path` that holds its engine's
    loop, and that thread's inclusive counts of ENGINE_PARTS."""
    best = None
    for part in sorted(glob.glob(path + "-*")):
        costs, total = inclusive_one(part)
        turns = costs.get(ENGINE_PARTS[0], 0)
        if turns and (best is None or turns > best[1][ENGINE_PARTS[0]]):
            best = (part, {fn: costs.get(fn, 0) for fn in ENGINE_PARTS})
    return best


# Each thread's file is read twice (the render, then the engine threads):
# callgrind_annotate runs once a file.
@functools.lru_cache(maxsize=None)
def inclusive_one(path):
    out = subprocess.run(
        ["callgrind_annotate", "--inclusive=yes", "--threshold=100", "--auto=no", path],
        capture_output=True, text=True, check=True).stdout
    costs = {}
    total = 0
    for line in out.splitlines():
        m = re.match(r"\s*([\d,]+) \(\s*[\d.]+%\)\s+(.*)$", line)
        if not m:
            continue
        n = int(m.group(1).replace(",", ""))
        rest = m.group(2)
        if rest.strip() == "PROGRAM TOTALS":
            total = n
            continue
        fn = re.sub(r" \[.*\]$", "", rest.split(":", 1)[-1]).strip()
        fn = re.sub(r"'\d+$", "", fn)
        costs[fn] = max(costs.get(fn, 0), n)
    return costs, total


def self_costs(path):
    """Self (exclusive) instructions by function over callgrind's per-thread
    files `path-NN`, summed; a function's inlined pieces, which callgrind
    lists under their source files, are added into it."""
    costs = {}
    for part in sorted(glob.glob(path + "-*")):
        out = subprocess.run(
            ["callgrind_annotate", "--inclusive=no", "--threshold=100", "--auto=no", part],
            capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            m = re.match(r"\s*([\d,]+) \(\s*[\d.]+%\)\s+(.*)$", line)
            if not m or m.group(2).strip() == "PROGRAM TOTALS":
                continue
            fn = re.sub(r" \[.*\]$", "", m.group(2).split(":", 1)[-1]).strip()
            costs[fn] = costs.get(fn, 0) + int(m.group(1).replace(",", ""))
    return costs


def small_scene(src, dst, width, height, spp):
    """A copy of scene `src` at another size, its mesh paths made absolute."""
    base = os.path.dirname(os.path.abspath(src))
    text = open(src).read()
    text = re.sub(r"resolution\s*=\s*\[[^\]]*\]", f"resolution = [{width}, {height}]", text)
    if re.search(r"^spp\s*=", text, re.M):
        text = re.sub(r"^spp\s*=.*$", f"spp = {spp}", text, flags=re.M)
    text = re.sub(r'file\s*=\s*"([^"]+)"',
                  lambda m: 'file = "%s"' % os.path.join(base, m.group(1)), text)
    with open(dst, "w") as f:
        f.write(text)


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--locus", default="target/release/locus")
    ap.add_argument("--scene", default="scenes/generated/room.toml")
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--height", type=int, default=72)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--fetch", default="forward")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1,
                    help="threads per worker; from 4 on the engine's thread only keeps the books, "
                         "so its instructions against the pool's say whether it holds the pool back")
    ap.add_argument("--cost", default="sampled",
                    help="the partition's cost model: `analytic` keeps the partition of a "
                         "build whose tracer counts nodes differently, for comparing two builds")
    ap.add_argument("--partitioner", default="region-growing")
    ap.add_argument("--shared-percent", type=int, default=10,
                    help="the scene's share every worker holds beside its region (0: regions only)")
    ap.add_argument("--per-thread", action="store_true",
                    help="print what each worker's engine thread spends by function")
    ap.add_argument("--self-costs", type=int, default=0, metavar="N",
                    help="print the N functions whose self instructions the farm's workers "
                         "spend most above one machine's, per ray and per forwarded query "
                         "(with LOCUS_CALLGRIND_ARGS' toggles, those of the toggled code only)")
    ap.add_argument("--out", default="bench-out/forward-cost")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    out = os.path.abspath(a.out)
    locus = os.path.abspath(a.locus)
    scene = os.path.join(out, "scene.toml")
    small_scene(a.scene, scene, a.width, a.height, a.spp)
    # One file per thread: the render is told from the setup thread by
    # thread (`render_by_thread`).
    cg = ["valgrind", "--tool=callgrind", "--separate-threads=yes"] + os.environ.get("LOCUS_CALLGRIND_ARGS", "").split()
    for old in glob.glob(os.path.join(out, "*.cg*")):
        os.remove(old)

    one_exr = os.path.join(out, "one.exr")
    subprocess.run(cg + [f"--callgrind-out-file={out}/one.cg", locus, "render", scene,
                         "--threads", "2", "-o", one_exr],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    one = inclusive(f"{out}/one.cg")[0]["locus_core::passes::pixel_mean"]

    port = free_port()
    token = ["--token", "forward-cost"]
    log = open(os.path.join(out, "farm.log"), "w")
    sched = subprocess.Popen([locus, "scheduler", "--listen", f"127.0.0.1:{port}",
                              "--worker-timeout", "600"] + token, stdout=log, stderr=log)
    # Fixed listen addresses tie each process's counts to its report row.
    listen = {i: f"127.0.0.1:{free_port()}" for i in range(1, a.workers + 1)}
    workers = [subprocess.Popen(cg + [f"--callgrind-out-file={out}/w{i}.cg", locus, "worker",
                                      "--scheduler", f"127.0.0.1:{port}",
                                      "--listen", listen[i], "--threads", str(a.threads),
                                      "--name", f"w{i}"] + token, stdout=log, stderr=log)
               for i in range(1, a.workers + 1)]
    farm_exr = os.path.join(out, "farm.exr")
    try:
        # The client waits for every worker to register.
        subprocess.run([locus, "submit", "--scheduler", f"127.0.0.1:{port}", scene,
                        "--workers", str(a.workers), "--fetch", a.fetch, "--cost", a.cost,
                        "--partitioner", a.partitioner,
                        "--shared-percent", str(a.shared_percent),
                        "-o", farm_exr] + token,
                       check=True, stdout=log, stderr=log, timeout=1800)
    finally:
        for w in workers:
            w.send_signal(signal.SIGINT)
        for w in workers:
            w.wait(timeout=120)
        sched.send_signal(signal.SIGINT)
        sched.wait(timeout=60)
    report = json.load(open(os.path.join(out, "farm.json")))["farm"]
    forwards = sum(w["stats"]["forwarded_out"] for w in report["workers"])
    same = subprocess.run([locus, "diff", one_exr, farm_exr, "--exact"],
                          capture_output=True, text=True).returncode == 0
    rows = []
    farm = 0
    for i in range(1, a.workers + 1):
        stats = next((w["stats"] for w in report["workers"] if w["addr"] == listen[i]), {})
        engine, pool, runtime, setup = render_by_thread(f"{out}/w{i}.cg")
        render = engine + pool + runtime - setup
        rows.append((f"w{i}", engine, runtime - setup, render, stats, pool))
        farm += render
    print(f"scene {a.scene} at {a.width}x{a.height}, {a.spp} spp, {a.workers} workers x {a.threads} threads, "
          f"{a.fetch}, {a.cost} cost, {a.partitioner}, {a.shared_percent}% shared")
    print(f"one machine's render: {one / 1e6:.1f} M instructions")
    for name, turns, runtime, render, st, pool in rows:
        t = st.get("trace", {})
        print(f"{name}: engine {turns / 1e6:.1f} M, "
              + (f"pool {pool / 1e6:.1f} M, " if pool else "")
              + f"runtime {runtime / 1e6:.1f} M, "
              f"render phase {render / 1e6:.1f} M; tiles {st.get('tiles', 0)}, "
              f"BVH steps {(t.get('bvh_nodes', 0) + t.get('tri_tests', 0)) / 1e6:.2f} M, "
              f"queries in {st.get('queries_in', 0)}, forwarded {st.get('forwarded_out', 0)}")
    print(f"forwarded queries: {forwards}")
    per = (farm - one) / max(forwards, 1)
    print(f"instructions per forwarded query beyond one machine: {per:.0f}")
    tr = report["totals"]["trace"]
    rays = tr["camera_rays"] + tr["shadow_rays"] + tr["indirect_rays"]
    print(f"instructions per ray beyond one machine: {(farm - one) / max(rays, 1):.0f} "
          f"({rays} rays, {forwards / max(rays, 1):.3f} forwarded per ray)")
    busiest = max(r[3] for r in rows)
    print(f"busiest worker's render phase over the workers' mean: "
          f"{busiest * len(rows) / max(farm, 1):.3f} ({busiest / 1e6:.1f} M)")
    print(f"farm image bit-identical to one machine's: {'yes' if same else 'NO'}")
    if a.per_thread:
        for i in range(1, a.workers + 1):
            found = engine_thread(f"{out}/w{i}.cg")
            if found is None:
                print(f"w{i}: no thread holds the engine's loop")
                continue
            part, parts = found
            print(f"w{i} engine thread ({os.path.basename(part)}), inclusive:")
            for fn in ENGINE_PARTS:
                print(f"  {parts[fn] / 1e6:8.1f} M  {fn}")
    if a.self_costs:
        base = self_costs(f"{out}/one.cg")
        farm_self = {}
        for i in range(1, a.workers + 1):
            for fn, n in self_costs(f"{out}/w{i}.cg").items():
                farm_self[fn] = farm_self.get(fn, 0) + n
        above = sorted(((n - base.get(fn, 0), fn) for fn, n in farm_self.items()), reverse=True)
        print("self instructions above one machine: per ray, per forwarded query, function")
        for n, fn in above[:a.self_costs]:
            print(f"  {n / max(rays, 1):8.0f} {n / max(forwards, 1):8.0f}  {fn[:100]}")
    json.dump({"one": one, "workers": rows, "forwards": forwards, "per_forward": per,
               "rays": rays,
               "busiest": busiest,
               "identical": same}, open(os.path.join(out, "forward-cost.json"), "w"), indent=1)
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
