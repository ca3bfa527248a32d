#!/usr/bin/env python3
"""A binary PLY (float x y z, list uchar int vertex_indices) of an OBJ of
triangles, for measuring the PLY loader: obj_to_ply.py IN.obj OUT.ply
(needs numpy). Materials and normals are dropped."""
import numpy as np, sys
v=[]; f=[]
with open(sys.argv[1]) as fh:
    for line in fh:
        if line.startswith('v '):
            v.append(line[2:])
        elif line.startswith('f '):
            f.append(line[2:])
V=np.loadtxt(v, dtype=np.float32)
F=np.array([[int(x.split('/')[0])-1 for x in l.split()] for l in f], dtype=np.int32)
assert F.shape[1]==3
with open(sys.argv[2],'wb') as out:
    out.write(f"ply\nformat binary_little_endian 1.0\nelement vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\nelement face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n".encode())
    out.write(V.astype('<f4').tobytes())
    rec=np.zeros(len(F), dtype=[('n','u1'),('i','<i4',3)]); rec['n']=3; rec['i']=F
    out.write(rec.tobytes())
