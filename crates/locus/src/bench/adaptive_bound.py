#!/usr/bin/env python3
"""What spreading samples by each pixel's noise could give (stop 73 and 76):
adaptive_bound.py PREFIX reads PREFIX_s*.exr (renders of one scene with
different seeds) and PREFIX_ref.exr (a converged render) and prints the
relMSE left at equal samples, pixel by pixel and in squares of pixels.
Needs numpy and OpenEXR."""
import OpenEXR, numpy as np, sys, glob
def load(p):
    f = OpenEXR.File(p)
    ch = f.parts[0].channels
    if 'RGB' in ch: return np.asarray(ch['RGB'].pixels, dtype=np.float64)
    return np.stack([np.asarray(ch[c].pixels, dtype=np.float64) for c in 'RGB'], -1)
pre = sys.argv[1]
imgs = np.stack([load(p) for p in sorted(glob.glob(pre + '_s*.exr'))])
ref = load(pre + '_ref.exr')
var = imgs.var(0, ddof=1)          # variance of a 16-spp pixel mean
v = (var / (ref**2 + 1e-2)).mean(-1)  # relMSE's per-pixel term
print('pixels', v.size, 'mean v', v.mean())
even = v.mean()
for t in [1, 2, 4, 8, 16]:
    h, w = v.shape
    vt = v[:h//t*t, :w//t*t].reshape(h//t, t, w//t, t).mean((1, 3))
    print(f'tile {t}: sqrt-alloc relMSE / even = {np.sqrt(vt).mean()**2 / vt.mean():.3f}')
