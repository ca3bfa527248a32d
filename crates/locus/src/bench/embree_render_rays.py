#!/usr/bin/env python3
"""Traces a render's own rays with Embree, kind by kind (stop 81).

`split_probe` (an example of the locus crate) writes, with
SPLIT_PROBE_DUMP=DIR, the scene's triangles (DIR/tris.f32, nine floats each)
and every query of its render by kind (camera.f32, continuation.f32,
shadow.f32: origin, direction, start and end, eight floats each). This
traces each kind with Embree through the `embreex` package (pip install
embreex numpy), one ray at a time on one thread (its `run` calls
rtcIntersect1 or rtcOccluded1 per ray, with the extension's own cost per
ray), and prints the best of five rounds in nanoseconds a query, beside
what `split_probe` prints for locus on the same rays.

    SPLIT_PROBE_DUMP=DIR cargo run --release -p locus --example split_probe -- SCENE 2 3
    OMP_NUM_THREADS=1 python3 crates/locus/src/bench/embree_render_rays.py DIR
"""

import sys
import time

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh


def main():
    d = sys.argv[1]
    tris = np.fromfile(f"{d}/tris.f32", dtype=np.float32).reshape(-1, 3, 3)
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, tris)
    for kind in ["camera", "continuation", "shadow"]:
        q = np.fromfile(f"{d}/{kind}.f32", dtype=np.float32).reshape(-1, 8)
        o = np.ascontiguousarray(q[:, :3])
        dirs = np.ascontiguousarray(q[:, 3:6])
        # Every query starts at 0; an open end is passed as a large one.
        far = np.ascontiguousarray(np.where(np.isfinite(q[:, 7]), q[:, 7], 1e30).astype(np.float32))
        scene.run(o[:1], dirs[:1])  # the first query builds the BVH
        best = float("inf")
        for _ in range(5):
            t = time.perf_counter()
            if kind == "shadow":
                scene.run(o, dirs, dists=far, query="OCCLUDED")
            else:
                scene.run(o, dirs, dists=far)
            best = min(best, time.perf_counter() - t)
        print(f"{kind}: {len(q)} queries, {best * 1e9 / len(q):.1f} ns each (best of 5)")


main()
