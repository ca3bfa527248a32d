//! The sampled preview's tracing: camera samples and their paths traced
//! leaf by leaf through the scene, each leaf's work counted ([`Tally`]),
//! and each ray's run of leaves kept in the walks that
//! [`Preview::crossings_beside`], [`Preview::first_leaves`] and
//! [`Preview::charged`] follow.

use super::{
    Geometry, ORIGIN_COST, PATH_END, Preview, SHADOW_END, VERTEX_COST, WALK_END, camera_leaf,
};
use locus_core::geometry::Ray;
use locus_core::integrator::{DIM_PIXEL, PathRay, interpolate_normal, shade};
use locus_core::light::LightSet;
use locus_core::octree::Octree;
use locus_core::sampler::SampleKey;
use locus_core::scene::Scene;
use locus_core::stats::TraceStats;
use std::ops::ControlFlow;

/// What one thread of the preview counts.
struct Tally {
    cost: Vec<u64>,
    rays: u64,
    steps: u64,
    walks: Vec<u32>,
    walk_costs: Vec<u32>,
    pixels: Vec<(u32, u32)>,
}

impl Tally {
    fn new(n: usize) -> Self {
        Self {
            cost: vec![0; n],
            rays: 0,
            steps: 0,
            walks: Vec::new(),
            walk_costs: Vec::new(),
            pixels: Vec::new(),
        }
    }

    /// Ends a ray's run, a path's, or adds leaf `l` to the run.
    fn push_walk(&mut self, l: u32) {
        self.walks.push(l);
        self.walk_costs.push(0);
    }

    /// Adds `c` to leaf `l`'s cost and, where `l` is the walks' entry
    /// `at`, to that entry's.
    fn charge(&mut self, l: u32, at: Option<usize>, c: u64) {
        self.cost[l as usize] += c;
        if let Some(i) = at.filter(|&i| self.walks[i] == l) {
            let w = &mut self.walk_costs[i];
            *w = w.saturating_add(c.min(u32::MAX as u64) as u32);
        }
    }

    fn merge(mut self, o: Tally) -> Tally {
        for (x, y) in self.cost.iter_mut().zip(o.cost) {
            *x += y;
        }
        self.rays += o.rays;
        self.steps += o.steps;
        self.walks.extend(o.walks);
        self.walk_costs.extend(o.walk_costs);
        self.pixels.extend(o.pixels);
        self
    }
}

/// Traces one camera sample per preview pixel (the image downscaled by
/// `div`) with up to `bounces` diffuse bounces and a shadow ray per vertex,
/// every ray leaf by leaf, counting per-leaf work.
pub fn preview(
    scene: &Scene,
    tree: &Octree,
    accel: &dyn Geometry,
    lights: &LightSet,
    div: u32,
    bounces: u32,
    seed: u64,
) -> Preview {
    use rayon::prelude::*;
    let cam = &scene.camera;
    let shared = camera_leaf(tree, cam);
    let div = div.max(1);
    let (w, h) = (cam.width.div_ceil(div), cam.height.div_ceil(div));
    let n = tree.leaves.len();
    let t = (0..h)
        .into_par_iter()
        .fold(
            || Tally::new(n),
            |mut t, py| {
                for px in 0..w {
                    let (x, y) = (
                        (px * div).min(cam.width - 1),
                        (py * div).min(cam.height - 1),
                    );
                    let key =
                        SampleKey::independent(y as u64 * cam.width as u64 + x as u64, 0, seed);
                    let mut q = PathRay::camera(cam.ray(x, y, key.get2d(DIM_PIXEL)), key);
                    for bounce in 0..=bounces {
                        t.rays += 1;
                        let run = t.walks.len();
                        let (found, first) =
                            leafwise(tree, accel, &q.ray, f32::INFINITY, false, shared, &mut t);
                        // The ray's first entry in the walks, and its last
                        // (before its end marker): where it started and hit.
                        let entries = (run < t.walks.len()).then(|| (run, t.walks.len() - 2));
                        if let Some(l) = first.filter(|_| bounce == 0) {
                            t.charge(l, entries.map(|e| e.0), ORIGIN_COST);
                        }
                        let Some((hit, leaf)) = found else {
                            break;
                        };
                        t.charge(leaf, entries.map(|e| e.1), VERTEX_COST);
                        let i = hit.tri as usize;
                        let mat = &scene.materials[scene.tri_material[i] as usize];
                        let s = shade(
                            &q,
                            &hit,
                            &scene.tris[i],
                            scene.tri_normals.get(i).map_or(glam::Vec3::ZERO, |n| {
                                interpolate_normal(n, hit.b1, hit.b2)
                            }),
                            mat,
                            lights,
                            bounces,
                            None,
                            None,
                        );
                        if let Some(sr) = s.shadow {
                            t.rays += 1;
                            leafwise(tree, accel, &sr.ray, sr.t_max, true, shared, &mut t);
                        }
                        match s.next {
                            Some(nq) => q = nq,
                            None => break,
                        }
                    }
                    t.push_walk(PATH_END);
                    t.pixels.push((x, y));
                }
                t
            },
        )
        .reduce(|| Tally::new(n), Tally::merge);
    let mut pv = Preview {
        cost: t.cost.into_iter().map(|c| c as f64).collect(),
        rays: t.rays,
        steps: t.steps,
        paths: w as u64 * h as u64,
        crossings: super::Crossings::default(),
        walks: t.walks,
        walk_costs: t.walk_costs,
        pixels: t.pixels,
    };
    pv.crossings = pv.crossings_beside(&[]);
    pv
}

/// Traces `ray` one leaf interval at a time, adding each interval's BVH
/// work to its leaf; returns the hit with its leaf (for any-hit rays:
/// none), and the first leaf along the ray.
///
/// A leaf without triangles is everyone's on the farm: whoever holds the
/// ray crosses it, so no query is forwarded into it. So is the `shared`
/// leaf, the camera's, which every worker holds ([`camera_leaf`]); the
/// first leaf along the ray is the first other one. Its interval's work
/// goes to the leaf with triangles the ray last left (or, before the
/// first, the first it enters), and the run of leaves with triangles it
/// goes through is kept in the walks (a crossing between two of them,
/// however much empty space lies between, is counted from there:
/// [`Preview::crossings_beside`]).
fn leafwise(
    tree: &Octree,
    accel: &dyn Geometry,
    ray: &Ray,
    t_max: f32,
    any: bool,
    shared: Option<u32>,
    t: &mut Tally,
) -> (Option<(locus_core::accel::Hit, u32)>, Option<u32>) {
    let mut found = None;
    let mut first = None;
    let mut prev: Option<u32> = None;
    // Work in empty leaves before the first leaf with triangles, and the
    // last leaf crossed (which takes that work if no such leaf follows).
    let mut unowned = 0;
    let mut last = None;
    let run = t.walks.len();
    let _ = tree.walk(ray, 0.0, t_max, |leaf, ta, tb| {
        last = Some(leaf);
        let everyones = Some(leaf) == shared;
        if !everyones {
            first.get_or_insert(leaf);
        }
        let held = !everyones && !tree.leaves[leaf as usize].tris.is_empty();
        if held {
            match prev.replace(leaf) {
                Some(p) if p != leaf => t.push_walk(leaf),
                Some(_) => {}
                None => {
                    t.push_walk(leaf);
                    let c = std::mem::take(&mut unowned);
                    t.charge(leaf, Some(t.walks.len() - 1), c);
                }
            }
        }
        let mut st = TraceStats::default();
        let hit = if any {
            accel.occluded(ray, ta, tb, &mut st).then_some(None)
        } else {
            accel.closest(ray, ta, tb, &mut st).map(Some)
        };
        let steps = st.bvh_nodes + st.tri_tests;
        match prev {
            Some(p) => t.charge(p, Some(t.walks.len() - 1), steps),
            None => unowned += steps,
        }
        t.steps += steps;
        match hit {
            Some(h) => {
                found = h.map(|h| (h, leaf));
                ControlFlow::Break(())
            }
            None => ControlFlow::Continue(()),
        }
    });
    // A ray that stayed in one leaf is kept too: a path's first leaf may
    // be the only one its camera ray enters.
    if t.walks.len() > run {
        t.push_walk(if any { SHADOW_END } else { WALK_END });
    }
    if let Some(l) = last.filter(|_| unowned > 0) {
        t.cost[l as usize] += unowned;
    }
    (found, first)
}
