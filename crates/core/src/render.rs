//! Single-machine rendering: prepare a scene (octree, BVH, lights), then
//! render tiles on a rayon compute pool.
//!
//! Each pixel's samples are evaluated and summed in the order of
//! [`crate::passes`] by one task, so the image is bit-identical for any thread count and any
//! tile order. Non-finite sample values are replaced by zero and counted.

use crate::accel::Accel;
use crate::dircache::{CacheMemory, CacheParams, LeafCaches};
use crate::geometry::{Bounds, TriangleSet};
use crate::image_io::Image;
use crate::irradiance::IrradianceParams;
use crate::irradiance::overture::{self, OvertureStats};
use crate::light::LightSet;
use crate::metrics::{ErrorEstimate, estimate_error};
use crate::octree::Octree;
use crate::passes::{PixelSum, pixel_mean};
use crate::path::{CacheUse, ChainVertex, Kernel, WholeScene};
use crate::sampler::{Sampler, mix64};
use crate::scene::Scene;
use crate::stats::TraceStats;
use serde::Serialize;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// A scene ready to trace.
pub struct Prepared {
    pub scene: Scene,
    /// A BVH over every triangle, with their materials.
    pub accel: Accel,
    pub lights: LightSet,
    pub timings: PrepTimings,
    /// Built on first use: only directional caches need it on one machine.
    octree: OnceLock<(Octree, f64)>,
}

#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct PrepTimings {
    pub bvh_s: f64,
}

/// The BVH over every triangle of `scene` that one machine traces.
pub fn whole_scene_accel(scene: &Scene) -> Accel {
    let set = TriangleSet {
        ids: (0..scene.tris.len() as u32).collect(),
        verts: scene.tris.clone(),
        material: scene.tri_material.clone(),
        normals: scene.tri_normals.clone(),
    };
    Accel::from_set(set, scene.magnitude())
}

impl Prepared {
    pub fn new(scene: Scene) -> Self {
        let t = Instant::now();
        let accel = whole_scene_accel(&scene);
        let bvh_s = t.elapsed().as_secs_f64();
        let lights = LightSet::build(&scene);
        if lights.is_empty() {
            tracing::warn!(scene = %scene.path.display(), "scene has no emitters: the image will be black");
        }
        Self {
            scene,
            accel,
            lights,
            timings: PrepTimings { bvh_s },
            octree: OnceLock::new(),
        }
    }

    /// The scene's octree (the one the farm partitions and the directional
    /// caches live on), built on first use.
    pub fn octree(&self) -> &Octree {
        &self.octree_timed().0
    }

    /// Seconds the octree took, if it was built.
    pub fn octree_s(&self) -> Option<f64> {
        self.octree.get().map(|o| o.1)
    }

    fn octree_timed(&self) -> &(Octree, f64) {
        self.octree.get_or_init(|| {
            let t = Instant::now();
            let o = Octree::build(&self.scene.tris, self.scene.settings.octree);
            (o, t.elapsed().as_secs_f64())
        })
    }

    /// The path kernel over this scene.
    pub fn kernel<'a>(&'a self, max_depth: u32, cache: Option<CacheUse<'a>>) -> Kernel<'a> {
        Kernel {
            cache,
            ..Kernel::exact(
                &self.scene.materials,
                &self.lights,
                &self.scene.camera,
                self.scene.settings.seed,
                self.scene.settings.sampler,
                max_depth,
            )
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
    pub sampler: Sampler,
    /// 0 means all cores.
    pub threads: usize,
    pub tile_size: u32,
    pub tile_order: TileOrder,
    /// Directional caches on the octree's leaves.
    pub cache: Option<CacheParams>,
    /// Ward's irradiance cache at the first vertex.
    pub irradiance: Option<IrradianceParams>,
}

impl RenderOptions {
    pub fn from_scene(scene: &Scene) -> Self {
        Self {
            spp: scene.settings.spp,
            max_depth: scene.settings.max_depth,
            seed: scene.settings.seed,
            sampler: scene.settings.sampler,
            threads: 0,
            tile_size: 16,
            tile_order: TileOrder::Scanline,
            cache: None,
            irradiance: None,
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

impl Tile {
    pub fn pixels(&self) -> u32 {
        (self.x1 - self.x0) * (self.y1 - self.y0)
    }
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

/// The value of one pixel: its samples in passes, averaged
/// ([`crate::passes`]). `chain` is scratch the caller keeps from pixel to
/// pixel, so a path's vertices are not allocated again for every pixel.
pub fn render_pixel(
    kernel: &Kernel,
    tracer: &WholeScene,
    (x, y): (u32, u32),
    spp: u32,
    chain: &mut Vec<ChainVertex>,
    stats: &mut TraceStats,
) -> PixelSum {
    pixel_mean(spp, stats, |s, st| {
        kernel.sample(tracer, x, y, s, chain, st)
    })
}

pub struct RenderOutput {
    pub image: Image,
    pub stats: TraceStats,
    pub render_s: f64,
    /// Each pixel mean's variance, from its samples' spread (None for one
    /// sample a pixel).
    pub variance: Option<Image>,
    /// The error the image carries, read from `variance`.
    pub error_estimate: Option<ErrorEstimate>,
    /// What the directional caches held at the end, when they were on.
    pub cache_memory: Option<CacheMemory>,
    /// How the irradiance cache was built, when it was on.
    pub irradiance: Option<OvertureStats>,
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
        .map(|p| LeafCaches::new(prep.octree().leaves.len(), p));
    let mut kernel = prep.kernel(
        opts.max_depth,
        caches.as_ref().map(|c| CacheUse {
            octree: prep.octree(),
            caches: c,
        }),
    );
    kernel.seed = opts.seed;
    kernel.sampler = opts.sampler;
    let tracer = WholeScene(&prep.accel);
    let tl = tiles(cam.width, cam.height, opts.tile_size, opts.tile_order);
    let total = tl.len();
    let done = AtomicUsize::new(0);
    let start = Instant::now();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.threads)
        .build()
        .expect("thread pool");
    // The overture fills the irradiance cache; the render only reads it.
    // It measures without the directional caches, as the farm's measurers
    // do, so the records are the same wherever they are made.
    let ambient = opts.irradiance.map(|p| {
        let bounds = Bounds::of_triangles(&prep.scene.tris);
        pool.install(|| overture::build(&kernel.without_caches(), &tracer, p, &bounds))
    });
    kernel.irradiance = ambient.as_ref().map(|a| &a.0);
    let results: Vec<(Tile, Vec<PixelSum>, TraceStats)> = pool.install(|| {
        tl.par_iter()
            .map(|t| {
                let mut st = TraceStats::default();
                let mut px = Vec::with_capacity(((t.x1 - t.x0) * (t.y1 - t.y0)) as usize);
                let mut chain = Vec::with_capacity(kernel.max_depth as usize + 1);
                for y in t.y0..t.y1 {
                    for x in t.x0..t.x1 {
                        let p =
                            render_pixel(&kernel, &tracer, (x, y), opts.spp, &mut chain, &mut st);
                        px.push(p);
                    }
                }
                progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                (*t, px, st)
            })
            .collect()
    });
    let (image, variance, stats) = assemble(cam.width, cam.height, opts.spp, results);
    let error_estimate = variance
        .as_ref()
        .map(|v| estimate_error(&image, v, opts.spp));
    let render_s = duration_s(start.elapsed());
    RenderOutput {
        image,
        stats,
        render_s,
        variance,
        error_estimate,
        cache_memory: caches.map(|c| c.memory()),
        irradiance: ambient.map(|a| a.1),
    }
}

/// The image, each pixel mean's variance (None for one sample a pixel)
/// and the counters, from the tiles' pixel sums.
fn assemble(
    width: u32,
    height: u32,
    spp: u32,
    results: Vec<(Tile, Vec<PixelSum>, TraceStats)>,
) -> (Image, Option<Image>, TraceStats) {
    let mut image = Image::new(width, height);
    let mut variance = (spp > 1).then(|| Image::new(width, height));
    let mut stats = TraceStats::default();
    for (t, px, st) in results {
        let mut sums = px.iter();
        for y in t.y0..t.y1 {
            for (x, p) in (t.x0..t.x1).zip(&mut sums) {
                let i = (y * width + x) as usize;
                image.pixels[i] = p.mean(spp);
                if let (Some(v), Some(var)) = (variance.as_mut(), p.variance_of_mean_f32(spp)) {
                    v.pixels[i] = var;
                }
            }
        }
        stats += st;
    }
    (image, variance, stats)
}

fn duration_s(d: Duration) -> f64 {
    d.as_secs_f64()
}
