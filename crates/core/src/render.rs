//! Single-machine rendering: prepare a scene (octree, BVH, lights), then
//! render tiles on a rayon compute pool.
//!
//! Each pixel's samples are evaluated and summed in sample-index order by
//! one task, so the image is bit-identical for any thread count and any
//! tile order. Non-finite sample values are replaced by zero and counted.

use crate::accel::Accel;
use crate::dircache::{CacheMemory, CacheParams, LeafCaches};
use crate::image_io::Image;
use crate::integrator::{CacheUse, DIM_PIXEL, Integrator};
use crate::light::LightSet;
use crate::octree::Octree;
use crate::sampler::{SampleKey, mix64};
use crate::scene::Scene;
use crate::stats::TraceStats;
use glam::Vec3;
use serde::Serialize;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// A scene ready to trace.
pub struct Prepared {
    pub scene: Scene,
    pub octree: Octree,
    pub accel: Accel,
    pub lights: LightSet,
    pub timings: PrepTimings,
}

#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct PrepTimings {
    pub octree_s: f64,
    pub bvh_s: f64,
}

impl Prepared {
    pub fn new(scene: Scene) -> Self {
        let t = Instant::now();
        let octree = Octree::build(&scene.tris, scene.settings.octree);
        let octree_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let ids: Vec<u32> = (0..scene.tris.len() as u32).collect();
        let accel = Accel::build(&scene.tris, &ids, scene.magnitude());
        let bvh_s = t.elapsed().as_secs_f64();
        let lights = LightSet::build(&scene);
        if lights.is_empty() {
            tracing::warn!(scene = %scene.path.display(), "scene has no emitters: the image will be black");
        }
        Self {
            scene,
            octree,
            accel,
            lights,
            timings: PrepTimings { octree_s, bvh_s },
        }
    }

    /// The integrator without caches.
    pub fn integrator(&self, max_depth: u32) -> Integrator<'_> {
        Integrator {
            scene: &self.scene,
            accel: &self.accel,
            lights: &self.lights,
            max_depth,
            cache: None,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum TileOrder {
    Scanline,
    Reverse,
    /// Shuffled by the given seed.
    Shuffled(u64),
}

#[derive(Clone, Copy, Debug, Serialize)]
pub struct RenderOptions {
    pub spp: u32,
    pub max_depth: u32,
    pub seed: u64,
    /// 0 means all cores.
    pub threads: usize,
    pub tile_size: u32,
    pub tile_order: TileOrder,
    /// Directional caches on the octree's leaves.
    pub cache: Option<CacheParams>,
}

impl RenderOptions {
    pub fn from_scene(scene: &Scene) -> Self {
        Self {
            spp: scene.settings.spp,
            max_depth: scene.settings.max_depth,
            seed: scene.settings.seed,
            threads: 0,
            tile_size: 16,
            tile_order: TileOrder::Scanline,
            cache: None,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Tile {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

pub fn tiles(width: u32, height: u32, size: u32, order: TileOrder) -> Vec<Tile> {
    let size = size.max(1);
    let mut v = Vec::new();
    for y0 in (0..height).step_by(size as usize) {
        for x0 in (0..width).step_by(size as usize) {
            v.push(Tile {
                x0,
                y0,
                x1: (x0 + size).min(width),
                y1: (y0 + size).min(height),
            });
        }
    }
    match order {
        TileOrder::Scanline => {}
        TileOrder::Reverse => v.reverse(),
        TileOrder::Shuffled(seed) => {
            // Fisher-Yates with a counter-based generator.
            for i in (1..v.len()).rev() {
                let j = (mix64(seed ^ i as u64) % (i as u64 + 1)) as usize;
                v.swap(i, j);
            }
        }
    }
    v
}

/// The value of one pixel: its samples in index order, averaged.
pub fn render_pixel(
    integ: &Integrator,
    camera: &crate::scene::Camera,
    x: u32,
    y: u32,
    spp: u32,
    seed: u64,
    stats: &mut TraceStats,
) -> [f32; 3] {
    let pixel = y as u64 * camera.width as u64 + x as u64;
    let mut sum = glam::DVec3::ZERO;
    for s in 0..spp {
        let key = SampleKey::new(pixel, s, seed);
        let ray = camera.ray(x, y, key.get2d(DIM_PIXEL));
        let l: Vec3 = integ.radiance(ray, key, stats);
        stats.samples += 1;
        if l.is_finite() {
            sum += l.as_dvec3();
        } else {
            stats.invalid_samples += 1;
        }
    }
    let m = sum / spp as f64;
    [m.x as f32, m.y as f32, m.z as f32]
}

pub struct RenderOutput {
    pub image: Image,
    pub stats: TraceStats,
    pub render_s: f64,
    /// What the directional caches held at the end, when they were on.
    pub cache_memory: Option<CacheMemory>,
}

/// Renders on a pool of `opts.threads` threads; `progress(done, total)` is
/// called after each tile.
pub fn render(
    prep: &Prepared,
    opts: &RenderOptions,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> RenderOutput {
    use rayon::prelude::*;
    let cam = &prep.scene.camera;
    let caches = opts
        .cache
        .map(|p| LeafCaches::new(prep.octree.leaves.len(), p));
    let integ = Integrator {
        cache: caches.as_ref().map(|c| CacheUse {
            octree: &prep.octree,
            caches: c,
        }),
        ..prep.integrator(opts.max_depth)
    };
    let tl = tiles(cam.width, cam.height, opts.tile_size, opts.tile_order);
    let total = tl.len();
    let done = AtomicUsize::new(0);
    let start = Instant::now();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.threads)
        .build()
        .expect("thread pool");
    let results: Vec<(Tile, Vec<[f32; 3]>, TraceStats)> = pool.install(|| {
        tl.par_iter()
            .map(|t| {
                let mut st = TraceStats::default();
                let mut px = Vec::with_capacity(((t.x1 - t.x0) * (t.y1 - t.y0)) as usize);
                for y in t.y0..t.y1 {
                    for x in t.x0..t.x1 {
                        px.push(render_pixel(
                            &integ, cam, x, y, opts.spp, opts.seed, &mut st,
                        ));
                    }
                }
                progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                (*t, px, st)
            })
            .collect()
    });
    let mut image = Image::new(cam.width, cam.height);
    let mut stats = TraceStats::default();
    for (t, px, st) in results {
        let mut k = 0;
        for y in t.y0..t.y1 {
            for x in t.x0..t.x1 {
                image.pixels[(y * cam.width + x) as usize] = px[k];
                k += 1;
            }
        }
        stats += st;
    }
    let render_s = duration_s(start.elapsed());
    RenderOutput {
        image,
        stats,
        render_s,
        cache_memory: caches.map(|c| c.memory()),
    }
}

fn duration_s(d: Duration) -> f64 {
    d.as_secs_f64()
}
