# Traces the rays that `locus bench --embree-python PY` wrote with Embree
# (the embreex package: `pip install embreex`), on one thread, for the
# tracer's figures against Embree. Reads argv[1]/tris.f32 (9 floats a
# triangle), rays.f32 (origin and direction, 6 floats a ray) and
# rounds.txt; writes argv[1]/embree.json: the best round's rays per second,
# the build time, and each ray's closest-hit distance (inf for a miss) in
# embree_t.f32, for locus to check that both found the same hits.
import json
import os
import sys
import time

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

d = sys.argv[1]
tris = np.fromfile(os.path.join(d, "tris.f32"), dtype=np.float32).reshape(-1, 3, 3)
rays = np.fromfile(os.path.join(d, "rays.f32"), dtype=np.float32).reshape(-1, 6)
rounds = int(open(os.path.join(d, "rounds.txt")).read())
origins = np.ascontiguousarray(rays[:, :3])
dirs = np.ascontiguousarray(rays[:, 3:])
t = time.perf_counter()
scene = rtcs.EmbreeScene()
TriangleMesh(scene, tris)
# The first query commits the scene (builds the BVH): time it apart.
scene.run(origins[:1], dirs[:1])
build = time.perf_counter() - t
best = float("inf")
for _ in range(rounds):
    t = time.perf_counter()
    scene.run(origins, dirs)
    best = min(best, time.perf_counter() - t)
out = scene.run(origins, dirs, output=1)
tfar = np.where(out["primID"] >= 0, out["tfar"], np.inf).astype(np.float32)
tfar.tofile(os.path.join(d, "embree_t.f32"))
with open(os.path.join(d, "embree.json"), "w") as f:
    json.dump({"mrays_per_s": len(rays) / best / 1e6, "build_s": build}, f)
