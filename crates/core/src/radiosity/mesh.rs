//! Patches and their elements.
//!
//! Each scene triangle is one patch, meshed by midpoint subdivision into
//! elements: an element tree per patch whose leaves are the elements. The
//! radiosity lives at element corners (Wallace's vertex radiosity), so the
//! solution interpolates smoothly across an element and a criterion on
//! corner differences decides where to subdivide. Corners are addressed by
//! integer barycentric lattice coordinates `(i, j)` over `2^levels`
//! divisions of the patch, which makes a corner that two elements share
//! the same vertex, and a midpoint created by one element's split the
//! same vertex its neighbour's split would create.
//!
//! Both sides of a patch carry a radiosity, because the path tracer's
//! surfaces reflect on both sides; only the front (the side of
//! `(v1 - v0) x (v2 - v0)`) emits, as in the path tracer.

use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// No children: the element is a leaf.
pub const LEAF: u32 = u32::MAX;

/// A corner shared by the elements of one patch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Vertex {
    /// Barycentric lattice coordinates over the patch's divisions.
    pub lattice: [u32; 2],
    pub pos: Vec3,
    /// Total radiosity (W/m^2) leaving each side: front, back.
    pub b: [Vec3; 2],
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Element {
    pub corners: [u32; 3],
    /// Index of the first of four children, or [`LEAF`].
    pub children: u32,
    pub level: u8,
}

/// One patch (a scene triangle), its element tree and its corners.
#[derive(Clone, Debug, PartialEq)]
pub struct Patch {
    pub tri: [Vec3; 3],
    /// Unit normal of the front side.
    pub normal: Vec3,
    pub area: f64,
    pub albedo: Vec3,
    /// Radiosity the front side emits: pi times the emitted radiance.
    pub emitted: Vec3,
    /// Radiosity received and reflected but not yet shot, per side.
    pub unshot: [DVec3; 2],
    /// The lattice has `2^levels` divisions per edge: the finest level an
    /// element of this patch may reach.
    pub levels: u32,
    pub vertices: Vec<Vertex>,
    /// `elements[0]` is the whole patch.
    pub elements: Vec<Element>,
    lattice: HashMap<u64, u32>,
}

fn key(l: [u32; 2]) -> u64 {
    ((l[0] as u64) << 32) | l[1] as u64
}

impl Patch {
    /// A patch meshed uniformly to `initial` levels, whose elements may be
    /// split down to `levels`.
    pub fn new(tri: [Vec3; 3], albedo: Vec3, radiance: Vec3, initial: u32, levels: u32) -> Self {
        let cross = (tri[1] - tri[0]).cross(tri[2] - tri[0]);
        let emitted = radiance * std::f32::consts::PI;
        let d = 1u32 << levels;
        let mut p = Self {
            tri,
            normal: cross.normalize_or_zero(),
            area: crate::geometry::tri_area_f64(&tri),
            albedo,
            emitted,
            unshot: [emitted.as_dvec3(), DVec3::ZERO],
            levels,
            vertices: Vec::new(),
            elements: Vec::new(),
            lattice: HashMap::new(),
        };
        let corners = [[0, 0], [d, 0], [0, d]].map(|l| p.vertex(l, [emitted, Vec3::ZERO]).0);
        p.elements.push(Element {
            corners,
            children: LEAF,
            level: 0,
        });
        let mut frontier = vec![0u32];
        for _ in 0..initial {
            let mut next = Vec::with_capacity(frontier.len() * 4);
            for e in frontier {
                let (first, _) = p.split(e, [emitted, Vec3::ZERO]);
                next.extend(first..first + 4);
            }
            frontier = next;
        }
        p
    }

    /// The position of lattice point `l`.
    pub fn position(&self, l: [u32; 2]) -> Vec3 {
        let d = (1u64 << self.levels) as f32;
        let (u, v) = (l[0] as f32 / d, l[1] as f32 / d);
        crate::geometry::hit_point(&self.tri, u, v)
    }

    /// The vertex at lattice point `l`, if there is one.
    pub fn vertex_id(&self, l: [u32; 2]) -> Option<u32> {
        self.lattice.get(&key(l)).copied()
    }

    /// The vertex at `l`, created with radiosity `init` if new; the flag
    /// says whether it was created.
    fn vertex(&mut self, l: [u32; 2], init: [Vec3; 2]) -> (u32, bool) {
        if let Some(&v) = self.lattice.get(&key(l)) {
            return (v, false);
        }
        let id = self.vertices.len() as u32;
        let pos = self.position(l);
        self.vertices.push(Vertex {
            lattice: l,
            pos,
            b: init,
        });
        self.lattice.insert(key(l), id);
        (id, true)
    }

    /// Splits leaf `e` into four; a midpoint that is new starts with
    /// radiosity `init`. Returns the first child and the vertices created.
    pub fn split(&mut self, e: u32, init: [Vec3; 2]) -> (u32, Vec<u32>) {
        let el = self.elements[e as usize];
        debug_assert_eq!(el.children, LEAF);
        let l = el.corners.map(|c| self.vertices[c as usize].lattice);
        let mid = |a: [u32; 2], b: [u32; 2]| [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2];
        let mut created = Vec::new();
        let mut m = [0u32; 3];
        for (k, (a, b)) in [(0, 1), (1, 2), (2, 0)].into_iter().enumerate() {
            let (v, new) = self.vertex(mid(l[a], l[b]), init);
            if new {
                created.push(v);
            }
            m[k] = v;
        }
        let [c0, c1, c2] = el.corners;
        let [m01, m12, m20] = m;
        let first = self.elements.len() as u32;
        let level = el.level + 1;
        for corners in [
            [c0, m01, m20],
            [m01, c1, m12],
            [m20, m12, c2],
            [m12, m20, m01],
        ] {
            self.elements.push(Element {
                corners,
                children: LEAF,
                level,
            });
        }
        self.elements[e as usize].children = first;
        (first, created)
    }

    /// Indices of the leaf elements, in tree order (none for a
    /// [`Self::shell`], whose mesh is on a farm's node).
    pub fn leaves(&self) -> Vec<u32> {
        let mut out = Vec::new();
        if self.elements.is_empty() {
            return out;
        }
        let mut stack = vec![0u32];
        while let Some(e) = stack.pop() {
            let c = self.elements[e as usize].children;
            if c == LEAF {
                out.push(e);
            } else {
                stack.extend((c..c + 4).rev());
            }
        }
        out
    }

    /// Area of an element: each level quarters it.
    pub fn element_area(&self, e: u32) -> f64 {
        self.area / (1u64 << (2 * self.elements[e as usize].level as u32)) as f64
    }

    /// The leaf holding the point with patch barycentrics `(b1, b2)`, and
    /// the point's barycentrics within it.
    pub fn locate(&self, b1: f32, b2: f32) -> (u32, [f32; 3]) {
        let d = (1u64 << self.levels) as f64;
        let p = [b1 as f64 * d, b2 as f64 * d];
        let mut e = 0u32;
        loop {
            let el = self.elements[e as usize];
            if el.children == LEAF {
                let w = self.lattice_barycentrics(e, p);
                return (e, w.map(|x| x.clamp(0.0, 1.0) as f32));
            }
            // The child the point lies deepest inside.
            e = (el.children..el.children + 4)
                .max_by(|&a, &b| {
                    let ma = self
                        .lattice_barycentrics(a, p)
                        .into_iter()
                        .fold(f64::MAX, f64::min);
                    let mb = self
                        .lattice_barycentrics(b, p)
                        .into_iter()
                        .fold(f64::MAX, f64::min);
                    ma.total_cmp(&mb).then(b.cmp(&a))
                })
                .unwrap_or(el.children);
        }
    }

    fn lattice_barycentrics(&self, e: u32, p: [f64; 2]) -> [f64; 3] {
        let c = self.elements[e as usize]
            .corners
            .map(|v| self.vertices[v as usize].lattice.map(|x| x as f64));
        let (x0, y0) = (c[1][0] - c[0][0], c[1][1] - c[0][1]);
        let (x1, y1) = (c[2][0] - c[0][0], c[2][1] - c[0][1]);
        let (px, py) = (p[0] - c[0][0], p[1] - c[0][1]);
        let det = x0 * y1 - x1 * y0;
        let w1 = (px * y1 - x1 * py) / det;
        let w2 = (x0 * py - px * y0) / det;
        [1.0 - w1 - w2, w1, w2]
    }

    /// Radiosity of `side` at barycentrics `w` of leaf `e`.
    pub fn radiosity_at(&self, e: u32, w: [f32; 3], side: usize) -> Vec3 {
        let c = self.elements[e as usize].corners;
        (0..3).fold(Vec3::ZERO, |acc, k| {
            acc + self.vertices[c[k] as usize].b[side] * w[k]
        })
    }

    /// Mean radiosity of `side` over the patch: each element's corner mean,
    /// weighted by its area.
    pub fn mean_radiosity(&self, side: usize) -> DVec3 {
        let mut sum = DVec3::ZERO;
        for e in self.leaves() {
            let c = self.elements[e as usize].corners;
            let m = c
                .iter()
                .map(|&v| self.vertices[v as usize].b[side].as_dvec3())
                .sum::<DVec3>();
            sum += m / 3.0 * self.element_area(e);
        }
        sum / self.area
    }

    /// Unshot power of `side` (W, mean of the channels): what the shooter
    /// choice maximises.
    pub fn unshot_power(&self, side: usize) -> f64 {
        let c = self.unshot[side];
        (c.x + c.y + c.z) / 3.0 * self.area
    }

    /// Keeps what a shot brought for the patch to shoot later: the part of
    /// the received power it reflects, as unshot radiosity.
    pub fn book(&mut self, r: &super::shoot::Receipt) {
        let rho = self.albedo.as_dvec3();
        for s in 0..2 {
            self.unshot[s] += rho * r.received[s] / self.area;
        }
    }

    /// The patch without its mesh: what a farm's coordinator keeps of a
    /// patch a worker holds, to choose shooters and keep the ledger.
    pub fn shell(&self) -> Patch {
        Patch {
            vertices: Vec::new(),
            elements: Vec::new(),
            lattice: HashMap::new(),
            ..*self
        }
    }

    /// Rebuilds a patch from its fields as they travel (a farm's node
    /// sends its patches to the coordinator), checking that the element
    /// tree and the lattice hold together, so that no later lookup can
    /// index out of bounds or loop.
    fn from_parts(p: PatchParts) -> Result<Self, String> {
        if p.levels > super::MAX_LEVELS {
            return Err(format!("a patch has {} lattice levels", p.levels));
        }
        if !(p.area.is_finite() && p.area > 0.0) {
            return Err("a patch has no positive area".into());
        }
        let d = 1u64 << p.levels;
        let mut lattice = HashMap::with_capacity(p.vertices.len());
        for (i, v) in p.vertices.iter().enumerate() {
            if v.lattice.iter().map(|&x| x as u64).sum::<u64>() > d {
                return Err(format!("patch vertex {i} lies off its lattice"));
            }
            if lattice.insert(key(v.lattice), i as u32).is_some() {
                return Err(format!("patch vertex {i} repeats a lattice point"));
            }
        }
        if p.elements.is_empty() {
            return Err("a patch has no elements".into());
        }
        let (nv, ne) = (p.vertices.len(), p.elements.len());
        for (i, e) in p.elements.iter().enumerate() {
            // Children after their parent: the tree cannot loop.
            let tree =
                e.children == LEAF || (e.children as usize > i && e.children as usize + 4 <= ne);
            if !tree || e.corners.iter().any(|&c| c as usize >= nv) || e.level as u32 > p.levels {
                return Err(format!(
                    "patch element {i} is not part of a valid element tree"
                ));
            }
        }
        Ok(Self {
            tri: p.tri,
            normal: p.normal,
            area: p.area,
            albedo: p.albedo,
            emitted: p.emitted,
            unshot: p.unshot,
            levels: p.levels,
            vertices: p.vertices,
            elements: p.elements,
            lattice,
        })
    }

    /// Bytes held by this patch's mesh.
    pub fn bytes(&self) -> usize {
        std::mem::size_of::<Self>()
            + self.vertices.capacity() * std::mem::size_of::<Vertex>()
            + self.elements.capacity() * std::mem::size_of::<Element>()
            + self.lattice.capacity() * (8 + 4 + 8)
    }
}

/// A patch as it travels: every field but the lattice index, which is
/// rebuilt on arrival.
#[derive(Serialize, Deserialize)]
struct PatchParts {
    tri: [Vec3; 3],
    normal: Vec3,
    area: f64,
    albedo: Vec3,
    emitted: Vec3,
    unshot: [DVec3; 2],
    levels: u32,
    vertices: Vec<Vertex>,
    elements: Vec<Element>,
}

/// [`PatchParts`] borrowed, so a patch is encoded without a copy.
#[derive(Serialize)]
struct PatchRef<'a> {
    tri: &'a [Vec3; 3],
    normal: &'a Vec3,
    area: f64,
    albedo: &'a Vec3,
    emitted: &'a Vec3,
    unshot: &'a [DVec3; 2],
    levels: u32,
    vertices: &'a [Vertex],
    elements: &'a [Element],
}

impl Serialize for Patch {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        PatchRef {
            tri: &self.tri,
            normal: &self.normal,
            area: self.area,
            albedo: &self.albedo,
            emitted: &self.emitted,
            unshot: &self.unshot,
            levels: self.levels,
            vertices: &self.vertices,
            elements: &self.elements,
        }
        .serialize(s)
    }
}

impl<'de> Deserialize<'de> for Patch {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        Patch::from_parts(PatchParts::deserialize(d)?).map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_patch_travels_whole_and_a_broken_one_is_refused() {
        let mut p = Patch::new(tri(), Vec3::splat(0.5), Vec3::ONE, 2, 5);
        let leaf = p.leaves()[5];
        p.split(leaf, [Vec3::X, Vec3::Y]);
        let json = serde_json::to_string(&p).unwrap();
        let q: Patch = serde_json::from_str(&json).unwrap();
        assert_eq!(q.leaves(), p.leaves());
        assert_eq!(q.vertex_id([4, 4]), p.vertex_id([4, 4]));
        assert_eq!(serde_json::to_string(&q).unwrap(), json);
        // A shell (the mesh away on a node) has no leaves and no radiosity,
        // and asking is no error.
        assert!(p.shell().leaves().is_empty());
        assert_eq!(p.shell().mean_radiosity(0), DVec3::ZERO);
        // A child index pointing back up the tree would loop.
        let mut bad = p.clone();
        bad.elements[1].children = 0;
        let e = serde_json::from_str::<Patch>(&serde_json::to_string(&bad).unwrap());
        assert!(e.unwrap_err().to_string().contains("element 1"));
        let mut bad = p.clone();
        bad.elements[2].corners[0] = 9999;
        assert!(serde_json::from_str::<Patch>(&serde_json::to_string(&bad).unwrap()).is_err());
        let mut bad = p;
        bad.vertices[3].lattice = [1 << 6, 0];
        assert!(serde_json::from_str::<Patch>(&serde_json::to_string(&bad).unwrap()).is_err());
    }

    fn tri() -> [Vec3; 3] {
        [
            Vec3::ZERO,
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(0.0, 3.0, 0.0),
        ]
    }

    #[test]
    fn uniform_meshing_shares_corners() {
        for initial in 0..4u32 {
            let p = Patch::new(tri(), Vec3::splat(0.5), Vec3::ZERO, initial, initial + 2);
            let n = 1usize << initial;
            assert_eq!(p.leaves().len(), n * n);
            // A triangular lattice of n divisions has (n+1)(n+2)/2 points.
            assert_eq!(p.vertices.len(), (n + 1) * (n + 2) / 2);
            let area: f64 = p.leaves().iter().map(|&e| p.element_area(e)).sum();
            assert!((area - 3.0).abs() < 1e-12);
        }
    }

    #[test]
    fn neighbours_share_the_midpoint_a_split_creates() {
        let mut p = Patch::new(tri(), Vec3::splat(0.5), Vec3::ZERO, 1, 4);
        let before = p.vertices.len();
        // The middle child shares an edge with each corner child.
        let (_, a) = p.split(4, [Vec3::ONE, Vec3::ZERO]);
        let (_, b) = p.split(1, [Vec3::ONE, Vec3::ZERO]);
        assert_eq!(a.len(), 3);
        assert_eq!(b.len(), 2, "one midpoint is shared with the middle child");
        assert_eq!(p.vertices.len(), before + 5);
    }

    #[test]
    fn locate_finds_the_leaf_holding_a_point() {
        let mut p = Patch::new(tri(), Vec3::splat(0.5), Vec3::ZERO, 2, 5);
        // Two levels deeper in places, so the descent crosses levels.
        let leaf = p.leaves()[3];
        let (first, _) = p.split(leaf, [Vec3::ZERO; 2]);
        p.split(first + 3, [Vec3::ZERO; 2]);
        p.split(p.leaves()[9], [Vec3::ZERO; 2]);
        let mut s = 7u64;
        for _ in 0..2000 {
            s = crate::sampler::mix64(s);
            let u = (s >> 40) as f32 / (1u64 << 24) as f32;
            let v = ((s >> 16) & 0xff_ffff) as f32 / (1u64 << 24) as f32;
            let (b1, b2) = if u + v > 1.0 {
                (1.0 - u, 1.0 - v)
            } else {
                (u, v)
            };
            let (e, w) = p.locate(b1, b2);
            assert_eq!(p.elements[e as usize].children, LEAF);
            let c = p.elements[e as usize].corners;
            let back = (0..3).fold(Vec3::ZERO, |a, k| a + p.vertices[c[k] as usize].pos * w[k]);
            let want = crate::geometry::hit_point(&p.tri, b1, b2);
            assert!((back - want).length() < 1e-4, "{back} vs {want}");
        }
    }
}
