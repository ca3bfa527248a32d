# Traces the rays that `locus bench --embree-python PY` wrote with Embree
# (the embreex package: `pip install embreex`), on one thread, for the
# tracer's figures against Embree. Reads argv[1]/tris.f32 (9 floats a
# triangle) and rays.f32 (origin and direction, 6 floats a ray), then
# answers locus line by line on its standard input and output, so that its
# rounds alternate with locus's own:
#   build  -> builds the scene, replies with the seconds it took;
#   round  -> traces every ray once, replies with the seconds it took;
#   hits   -> writes each ray's closest-hit distance (inf for a miss) to
#             argv[1]/embree_t.f32, for locus to check that both found the
#             same hits, replies "done" and exits.
import os
import sys
import time

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

d = sys.argv[1]
tris = np.fromfile(os.path.join(d, "tris.f32"), dtype=np.float32).reshape(-1, 3, 3)
rays = np.fromfile(os.path.join(d, "rays.f32"), dtype=np.float32).reshape(-1, 6)
origins = np.ascontiguousarray(rays[:, :3])
dirs = np.ascontiguousarray(rays[:, 3:])
scene = None
for line in sys.stdin:
    what = line.strip()
    if what == "build":
        t = time.perf_counter()
        scene = rtcs.EmbreeScene()
        TriangleMesh(scene, tris)
        # The first query commits the scene (builds the BVH).
        scene.run(origins[:1], dirs[:1])
        print(time.perf_counter() - t, flush=True)
    elif what == "round":
        t = time.perf_counter()
        scene.run(origins, dirs)
        print(time.perf_counter() - t, flush=True)
    elif what == "hits":
        out = scene.run(origins, dirs, output=1)
        tfar = np.where(out["primID"] >= 0, out["tfar"], np.inf).astype(np.float32)
        tfar.tofile(os.path.join(d, "embree_t.f32"))
        print("done", flush=True)
        break
    else:
        sys.exit(f"embree_trace.py: unknown request {what!r}")
