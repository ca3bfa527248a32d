#!/usr/bin/env python3
"""A locus scene from a pbrt-v4 scene of world-space meshes, for benchmarks.

It covers what the public scenes in ../shared/scenes use, and the usual
ways of placing a camera: the transform directives before `WorldBegin`
(`Transform`, `ConcatTransform`, `LookAt`, `Translate`, `Scale`,
`Rotate`, `Identity`, composed as pbrt composes them) and a perspective
`Camera` (`fov` on the image's shorter side),
`Film` resolution, `Integrator` maxdepth, `MakeNamedMaterial` and
`Material`, `NamedMaterial`, `Shape "plymesh"` and `Shape "trianglemesh"`
in world space, `AttributeBegin`/`AttributeEnd`, and `AreaLightSource
"diffuse"` with `rgb L`. locus models Lambertian surfaces only. Each pbrt
material becomes an albedo:
  - `diffuse`, `coateddiffuse` and `diffusetransmission`: their `rgb
    reflectance`, or 0.5 grey where it is a texture;
  - `conductor`: 0.6 grey;
  - `dielectric`: the shapes are left out, since a glass pane rendered as a
    diffuse wall would shut out the light behind it.
Every choice is printed. Any other directive inside the world block, such
as a transform or a texture used for alpha, stops the script rather than
give a different scene.

    python3 crates/locus/src/bench/pbrt_scene.py ../shared/scenes/kitchen/scene-v4.pbrt \\
        scenes/generated/kitchen.toml [--spp 16] [--scale-resolution 0.25]

The TOML names the PLY files by absolute path. Each `trianglemesh` is
written as an OBJ file beside the TOML.
"""

import argparse
import math
import os
import re
import sys

TOKEN = re.compile(r'"[^"]*"|\[|\]|[^\s\[\]"]+')


# How many quoted names a directive takes before its parameters (pbrt-v4's
# grammar); every other directive that takes any takes one.
POSITIONAL = {"Texture": 3, "MediumInterface": 2}


def tokens(text):
    """(line number, token) for each token, comments dropped."""
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0]
        for t in TOKEN.findall(line):
            yield n, t


def directives(path, text):
    """(name, positional strings, {param: values}, line) for each directive."""
    out, cur, names = [], None, 0
    numbered = list(tokens(text))
    toks = [t for _, t in numbered]
    toks.append("]")  # a list left open ends at the end of the file
    i = 0
    while i < len(numbered):
        t = toks[i]
        if t[0].isalpha():
            cur = [t, [], {}, numbered[i][0]]
            out.append(cur)
            names = 0
            i += 1
            continue
        # A quoted token is one of the directive's names (`Shape "plymesh"`,
        # `NamedMaterial "Wood floor"`, a name with a space included) while
        # it has fewer than it takes and no parameter came yet; after that,
        # a parameter's "type name".
        named = cur is not None and not cur[2] and names < POSITIONAL.get(cur[0], 1)
        if t.startswith('"') and cur is not None and not named:
            if " " not in t.strip('"'):
                sys.exit(f'{path}:{numbered[i][0]}: {t} where a parameter\'s "type name" belongs')
            key = t.strip('"')
            i += 1
            vals = []
            if i < len(toks) and toks[i] == "[":
                i += 1
                while toks[i] != "]":
                    vals.append(toks[i].strip('"'))
                    i += 1
                i += 1
            else:
                vals.append(toks[i].strip('"'))
                i += 1
            cur[2][key] = vals
            continue
        if t == "[" and cur is not None:
            # Transform [ 16 numbers ]
            i += 1
            while toks[i] != "]":
                cur[1].append(toks[i])
                i += 1
            i += 1
            continue
        if cur is None:
            sys.exit(f"{path}:{numbered[i][0]}: {t} before any directive")
        names += t.startswith('"')
        cur[1].append(t.strip('"'))
        i += 1
    return out


def param(params, name):
    for key, vals in params.items():
        if key.split()[-1] == name:
            return key.split()[0], vals
    return None, None


def albedo(params, name):
    kind = param(params, "type")[1][0] if "string type" in params else name
    if kind == "dielectric":
        return None, "dielectric: left out"
    if kind == "conductor":
        return [0.6, 0.6, 0.6], "conductor: grey 0.6"
    t, v = param(params, "reflectance")
    if t == "rgb":
        return [float(x) for x in v], f"{kind}: its reflectance"
    if t == "texture":
        return [0.5, 0.5, 0.5], f"{kind}: texture {v[0]}, grey 0.5"
    return [0.5, 0.5, 0.5], f"{kind}: no reflectance, grey 0.5"


def inverse_affine(m):
    """Inverse of a 4x4 affine matrix given as rows."""
    a = [row[:3] for row in m[:3]]
    t = [m[0][3], m[1][3], m[2][3]]
    det = (a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
           - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
           + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]))
    inv = [[0.0] * 3 for _ in range(3)]
    for r in range(3):
        for c in range(3):
            rr = [x for x in range(3) if x != c]
            cc = [x for x in range(3) if x != r]
            minor = a[rr[0]][cc[0]] * a[rr[1]][cc[1]] - a[rr[0]][cc[1]] * a[rr[1]][cc[0]]
            inv[r][c] = (-1) ** (r + c) * minor / det
    ti = [-sum(inv[r][c] * t[c] for c in range(3)) for r in range(3)]
    return inv, ti, det


IDENTITY = [[1.0 if r == c else 0.0 for c in range(4)] for r in range(4)]


def matmul(a, b):
    return [[sum(a[r][k] * b[k][c] for k in range(4)) for c in range(4)] for r in range(4)]


def normalize(v):
    n = math.sqrt(sum(x * x for x in v))
    return [x / n for x in v]


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def transform(name, pos, where):
    """The matrix (rows) of a transform directive, as pbrt-v4 builds it:
    `LookAt` gives camera-from-world, `Rotate` is in degrees about an
    axis."""
    try:
        v = [float(x) for x in pos]
    except ValueError:
        sys.exit(f"{where}: {name} takes numbers")
    want = {"Transform": 16, "ConcatTransform": 16, "LookAt": 9, "Translate": 3,
            "Scale": 3, "Rotate": 4, "Identity": 0}[name]
    if len(v) != want:
        sys.exit(f"{where}: {name} takes {want} numbers, not {len(v)}")
    if name in ("Transform", "ConcatTransform"):
        return [[v[c * 4 + r] for c in range(4)] for r in range(4)]  # columns in the file
    if name == "Identity":
        return IDENTITY
    if name == "Translate":
        return [[1, 0, 0, v[0]], [0, 1, 0, v[1]], [0, 0, 1, v[2]], [0, 0, 0, 1]]
    if name == "Scale":
        return [[v[0], 0, 0, 0], [0, v[1], 0, 0], [0, 0, v[2], 0], [0, 0, 0, 1]]
    if name == "Rotate":
        x, y, z = normalize(v[1:])
        s, c = math.sin(math.radians(v[0])), math.cos(math.radians(v[0]))
        return [[x * x + (1 - x * x) * c, x * y * (1 - c) - z * s, x * z * (1 - c) + y * s, 0],
                [x * y * (1 - c) + z * s, y * y + (1 - y * y) * c, y * z * (1 - c) - x * s, 0],
                [x * z * (1 - c) - y * s, y * z * (1 - c) + x * s, z * z + (1 - z * z) * c, 0],
                [0, 0, 0, 1]]
    eye, look, up = v[0:3], v[3:6], v[6:9]
    d = normalize([look[i] - eye[i] for i in range(3)])
    right = normalize(cross(normalize(up), d))
    new_up = cross(d, right)
    # camera-from-world: the inverse of the frame (right, up, d) at eye.
    rows = [right, new_up, d]
    return [r + [-sum(r[i] * eye[i] for i in range(3))] for r in rows] + [[0, 0, 0, 1]]


def apply(inv, ti, p, w=1.0):
    return [sum(inv[r][c] * p[c] for c in range(3)) + w * ti[r] for r in range(3)]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pbrt")
    ap.add_argument("out")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--scale-resolution", type=float, default=1.0)
    a = ap.parse_args()
    base = os.path.dirname(os.path.abspath(a.pbrt))
    outdir = os.path.dirname(os.path.abspath(a.out))
    stem = os.path.splitext(os.path.basename(a.out))[0]
    ds = directives(a.pbrt, open(a.pbrt).read())

    ctm, cam_ctm, cam, res, depth = IDENTITY, None, None, [640, 480], 8
    materials, named, current = {}, {}, None
    stack, meshes, lights, notes = [], [], [], []
    light_l = None
    in_world = False
    for name, pos, params, line in ds:
        where = f"{a.pbrt}:{line}"
        if name == "WorldBegin":
            in_world = True
        elif name in ("Transform", "Identity") and not in_world:
            ctm = transform(name, pos, where)
        elif name in ("ConcatTransform", "LookAt", "Translate", "Scale", "Rotate") and not in_world:
            ctm = matmul(ctm, transform(name, pos, where))
        elif name == "Camera":
            if pos[0] != "perspective":
                sys.exit(f"{where}: a {pos[0]} camera is not covered (a perspective one is)")
            _, fov = param(params, "fov")
            cam, cam_ctm = float(fov[0]) if fov else 90.0, ctm
        elif name == "Film":
            res = [int(param(params, "xresolution")[1][0]), int(param(params, "yresolution")[1][0])]
        elif name == "Integrator":
            t, v = param(params, "maxdepth")
            depth = int(v[0]) if v else depth
        elif name in ("Sampler", "PixelFilter", "Texture"):
            pass
        elif name == "MakeNamedMaterial":
            named[pos[0]] = params
        elif name == "NamedMaterial":
            current = ("named", pos[0])
        elif name == "Material":
            current = ("inline", dict(params, **{"string type": [pos[0]]}))
        elif name == "AttributeBegin":
            stack.append((current, light_l))
        elif name == "AttributeEnd":
            current, light_l = stack.pop()
        elif name == "AreaLightSource":
            t, v = param(params, "L")
            if t != "rgb":
                sys.exit(f"{where}: AreaLightSource with {t} L is not covered (rgb L is)")
            light_l = [float(x) for x in v]
        elif name == "Shape" and pos[0] in ("plymesh", "trianglemesh"):
            if light_l is not None:
                if pos[0] != "trianglemesh":
                    sys.exit(f"{where}: an emitting plymesh is not covered (a trianglemesh quad is)")
                p = [float(x) for x in param(params, "P")[1]]
                idx = [int(x) for x in param(params, "indices")[1]]
                _, n = param(params, "N")
                lights.append((p, idx, [float(x) for x in n] if n else None, light_l, where))
                continue
            if current is None:
                mat = "default"
            elif current[0] == "named":
                mat = current[1]
                if mat not in materials:
                    materials[mat] = albedo(named[mat], mat)
            else:
                mat = f"inline{len(materials)}"
                materials[mat] = albedo(current[1], mat)
            if materials.get(mat, ([0.5] * 3, ""))[0] is None:
                continue
            if pos[0] == "plymesh":
                meshes.append((os.path.join(base, param(params, "filename")[1][0]), mat))
            else:
                p = [float(x) for x in param(params, "P")[1]]
                idx = [int(x) for x in param(params, "indices")[1]]
                path = os.path.join(outdir, f"{stem}-mesh{len(meshes)}.obj")
                with open(path, "w") as f:
                    for k in range(0, len(p), 3):
                        f.write("v %r %r %r\n" % tuple(p[k:k + 3]))
                    for k in range(0, len(idx), 3):
                        f.write("f %d %d %d\n" % tuple(i + 1 for i in idx[k:k + 3]))
                meshes.append((path, mat))
        elif in_world:
            sys.exit(f"{where}: {name} {' '.join(pos[:1])} is not covered inside the world block; "
                     "remove it or extend pbrt_scene.py")

    if cam is None:
        sys.exit(f"{a.pbrt}: no Camera")
    inv, ti, det = inverse_affine(cam_ctm)
    eye = apply(inv, ti, [0, 0, 0])
    look = apply(inv, ti, [0, 0, 1])
    up = apply(inv, ti, [0, 1, 0], 0.0)
    w, h = (max(1, round(r * a.scale_resolution)) for r in res)
    # pbrt's fov is along the shorter side; locus's along the height.
    fov_y = cam if h <= w else math.degrees(2 * math.atan(math.tan(math.radians(cam) / 2) * h / w))
    out = [f"# Made by pbrt_scene.py from {os.path.abspath(a.pbrt)}",
           "[camera]", f"position = {eye}", f"look_at = {look}", f"up = {up}",
           f"fov_y = {fov_y}", f"resolution = [{w}, {h}]", "",
           "[render]", f"spp = {a.spp}", f"max_depth = {depth}", "seed = 1", ""]
    for mat, (alb, why) in sorted(materials.items()):
        notes.append(f"material {mat}: {why}")
        if alb is not None:
            out += [f'[materials."{mat}"]', f"albedo = {alb}", ""]
    for p, idx, n, le, where in lights:
        if len(p) != 12 or idx not in ([0, 1, 2, 0, 2, 3], [0, 2, 1, 0, 3, 2]):
            sys.exit(f"{where}: an emitter that is not one quad (4 points, 2 triangles) is not covered")
        v = [p[k:k + 3] for k in range(0, 12, 3)]
        ea = [v[1][i] - v[0][i] for i in range(3)]
        eb = [v[3][i] - v[0][i] for i in range(3)]
        cr = [ea[1] * eb[2] - ea[2] * eb[1], ea[2] * eb[0] - ea[0] * eb[2], ea[0] * eb[1] - ea[1] * eb[0]]
        if n and sum(cr[i] * n[i] for i in range(3)) < 0:
            ea, eb = eb, ea
        out += ["[[light]]", f"corner = {v[0]}", f"edge_a = {ea}", f"edge_b = {eb}", f"emission = {le}", ""]
    for path, mat in meshes:
        out += ["[[mesh]]", f'file = "{path}"', f'material = "{mat}"', ""]
    with open(a.out, "w") as f:
        f.write("\n".join(out))
    for line in notes:
        print(line)
    print(f"{len(meshes)} meshes, {len(lights)} lights, {w}x{h}, camera transform determinant {det:.3f}")


if __name__ == "__main__":
    main()
