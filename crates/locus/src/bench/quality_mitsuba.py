# Renders a scene that `locus bench quality` exported with Mitsuba 3, for
# its rows beside locus's. Reads the spec (JSON) named by argv[1]; writes each
# run's image as raw little-endian float32 RGB (rows top first), and the
# seconds each run took as JSON to argv[2] (Mitsuba logs to stdout).
#
# The scene is matched to locus's: a pinhole camera with a box pixel filter,
# two-sided diffuse surfaces with flat normals, one-sided area emitters on
# the triangles' front side, and Mitsuba's max_depth one more than locus's
# (Mitsuba counts the camera vertex). Russian roulette stays Mitsuba's own.
import json
import os
import sys
import time

import drjit as dr
import mitsuba as mi
import numpy as np


def transform(cam):
    t = mi.ScalarTransform4f
    try:
        return t().look_at(origin=cam["position"], target=cam["look_at"], up=cam["up"])
    except TypeError:
        return t.look_at(origin=cam["position"], target=cam["look_at"], up=cam["up"])


def scene_dict(spec, sampler, base):
    cam = spec["camera"]
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": spec["max_depth"]},
        "sensor": {
            "type": "perspective",
            "fov_axis": "y",
            "fov": cam["fov_y"],
            "to_world": transform(cam),
            "film": {
                "type": "hdrfilm",
                "width": cam["width"],
                "height": cam["height"],
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
            },
            "sampler": {"type": sampler, "sample_count": max(spec["spp"])},
        },
    }
    for i, m in enumerate(spec["meshes"]):
        mesh = {
            "type": "ply",
            "filename": os.path.join(base, m["ply"]),
            "face_normals": True,
            "bsdf": {
                "type": "twosided",
                "bsdf": {
                    "type": "diffuse",
                    "reflectance": {"type": "rgb", "value": m["albedo"]},
                },
            },
        }
        if max(m["emission"]) > 0:
            mesh["emitter"] = {
                "type": "area",
                "radiance": {"type": "rgb", "value": m["emission"]},
            }
        d[f"mesh{i}"] = mesh
    return d


def main():
    path = sys.argv[1]
    base = os.path.dirname(os.path.abspath(path))
    with open(path) as f:
        spec = json.load(f)
    mi.set_variant(spec["variant"])
    if spec["threads"] > 0:
        dr.set_thread_count(spec["threads"])
    times = []
    for sampler in spec["samplers"]:
        scene = mi.load_dict(scene_dict(spec, sampler, base))
        # Untimed: compiles the kernels, as a user's second render would find.
        np.array(mi.render(scene, spp=min(spec["spp"]), seed=1))
        for spp in spec["spp"]:
            t = time.perf_counter()
            img = np.array(mi.render(scene, spp=spp, seed=spp), dtype=np.float32)
            seconds = time.perf_counter() - t
            out = f"mitsuba-{sampler}-{spp}.f32"
            img.tofile(os.path.join(base, out))
            times.append(
                {"sampler": sampler, "spp": spp, "seconds": seconds, "image": out}
            )
    with open(sys.argv[2], "w") as f:
        json.dump({"version": mi.__version__, "runs": times}, f)


main()
