//! Single-machine rendering: prepare a scene (octree, BVH, lights), then
//! render tiles on a rayon compute pool.
//!
//! Each pixel's samples are evaluated and summed in the order of
//! [`crate::passes`] by one task, so the image is bit-identical for any thread count and any
//! tile order. Non-finite sample values are replaced by zero and counted.

use crate::accel::{Accel, BuildQuality};
use crate::dircache::{CacheMemory, CacheParams, LeafCaches};
use crate::geometry::{Bounds, TriangleSet};
use crate::image_io::Image;
use crate::irradiance::IrradianceParams;
use crate::irradiance::overture::{self, OvertureStats};
use crate::light::LightSet;
use crate::metrics::{ErrorEstimate, estimate_error, meets_target_counted};
use crate::octree::Octree;
use crate::passes::{Moments, PixelSum, pass_sum, passes, pixel_mean};
use crate::path::{CacheUse, ChainVertex, Kernel, Tracer, WholeScene};
use crate::sampler::{Sampler, mix64};
use crate::scene::Scene;
use crate::spread;
use crate::stats::TraceStats;
use serde::Serialize;
use std::ops::Range;
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
    /// The quality the BVH was built at.
    pub quality: BuildQuality,
}

/// The BVH over every triangle of `scene` that one machine traces.
pub fn whole_scene_accel(scene: &Scene) -> Accel {
    whole_scene_accel_with(scene, BuildQuality::Full)
}

/// [`whole_scene_accel`] at the quality asked for.
pub fn whole_scene_accel_with(scene: &Scene, quality: BuildQuality) -> Accel {
    let set = TriangleSet {
        ids: (0..scene.tris.len() as u32).collect(),
        verts: scene.tris.clone(),
        material: scene.tri_material.clone(),
        normals: scene.tri_normals.clone(),
    };
    Accel::from_set_with(set, scene.magnitude(), quality)
}

impl Prepared {
    /// The scene prepared with a [`BuildQuality::Full`] BVH: what tests,
    /// benchmarks of the tracer and long renders want.
    pub fn new(scene: Scene) -> Self {
        Self::with_quality(scene, BuildQuality::Full)
    }

    /// The scene prepared for a render of `spp` samples a pixel: its BVH
    /// built at the quality its settings ask for such a job
    /// ([`crate::accel::BvhSetting::quality`]), as the farm's workers
    /// build theirs for the same job.
    pub fn for_job(scene: Scene, spp: u32) -> Self {
        let samples = scene.camera.samples(spp);
        let quality = scene.settings.bvh.quality(samples, scene.tris.len() as u64);
        Self::with_quality(scene, quality)
    }

    /// The scene prepared with its BVH built at `quality`.
    pub fn with_quality(scene: Scene, quality: BuildQuality) -> Self {
        let t = Instant::now();
        let accel = whole_scene_accel_with(&scene, quality);
        let bvh_s = t.elapsed().as_secs_f64();
        let lights = LightSet::build(&scene);
        if lights.is_empty() {
            tracing::warn!(scene = %scene.path.display(), "scene has no emitters: the image will be black");
        }
        Self {
            scene,
            accel,
            lights,
            timings: PrepTimings { bvh_s, quality },
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
    /// Stop after the first pass whose estimated relMSE is at or below
    /// this; `spp` is then the most a pixel gets.
    pub target_rel_mse: Option<f64>,
    /// Adaptive sampling: the passes after the pilot spread their samples
    /// over the pixels by each one's noise ([`crate::spread`]), `spp` then
    /// being the mean a pixel gets.
    pub adaptive: bool,
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
            target_rel_mse: scene.settings.target_rel_mse,
            adaptive: scene.settings.adaptive_sampling,
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

/// One pass of pixel `(x, y)`: its samples `pass` summed in index order
/// ([`pass_sum`]). What one machine renders each pass of a noise-targeted
/// render with, and what a farm worker that holds the whole scene renders
/// a tile's pass with, on any tracer that finishes every segment.
pub fn pixel_pass<T: Tracer>(
    kernel: &Kernel,
    tracer: &T,
    (x, y): (u32, u32),
    pass: Range<u32>,
    chain: &mut Vec<ChainVertex>,
    st: &mut TraceStats,
) -> Moments {
    pass_sum(pass, st, |s, st| kernel.sample(tracer, x, y, s, chain, st))
}

pub struct RenderOutput {
    pub image: Image,
    /// Samples each pixel got: `spp`, or fewer where a noise target was
    /// met at the end of an earlier pass; with adaptive sampling, the mean
    /// a pixel got.
    pub spp: u32,
    /// With adaptive sampling, the samples each pixel got (row-major).
    pub sample_counts: Option<Vec<u32>>,
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
    // A render with a noise target or adaptive sampling goes over every
    // tile once a pass.
    let in_passes = opts.target_rel_mse.is_some() || opts.adaptive;
    let rounds = if in_passes { passes(opts.spp).len() } else { 1 };
    let total = tl.len() * rounds;
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
    let tick = || progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
    let (spp, results, sample_counts) = if in_passes {
        let how = InPasses {
            spp: opts.spp,
            target: opts.target_rel_mse,
            adaptive: opts.adaptive,
        };
        render_in_passes(&pool, &tl, &kernel, &tracer, how, &tick)
    } else {
        let pixel = |x, y, chain: &mut _, st: &mut _| {
            render_pixel(&kernel, &tracer, (x, y), opts.spp, chain, st)
        };
        (opts.spp, render_tiles(&pool, &tl, &tick, pixel), None)
    };
    let (image, variance, stats) = assemble(
        cam.width,
        cam.height,
        spp,
        sample_counts.as_deref(),
        results,
    );
    let error_estimate = variance.as_ref().map(|v| estimate_error(&image, v, spp));
    let render_s = duration_s(start.elapsed());
    RenderOutput {
        image,
        spp,
        sample_counts,
        stats,
        render_s,
        variance,
        error_estimate,
        cache_memory: caches.map(|c| c.memory()),
        irradiance: ambient.map(|a| a.1),
    }
}

/// A tile's pixels' sums and what tracing them counted.
type TileSums = (Tile, Vec<PixelSum>, TraceStats);

/// Each pixel of `tiles` as `pixel(x, y, chain, stats)` sums it, tiles in
/// parallel on `pool`; `tick` after each tile.
fn render_tiles(
    pool: &rayon::ThreadPool,
    tiles: &[Tile],
    tick: &(dyn Fn() + Sync),
    pixel: impl Fn(u32, u32, &mut Vec<ChainVertex>, &mut TraceStats) -> PixelSum + Sync,
) -> Vec<TileSums> {
    use rayon::prelude::*;
    pool.install(|| {
        // One tile a task: rayon's adaptive split otherwise leaves a thread
        // a run of tiles it cannot give away, which idles the others when
        // the tiles' costs differ (adaptive sampling's passes, a sky).
        tiles
            .par_iter()
            .with_max_len(1)
            .map(|t| {
                let mut st = TraceStats::default();
                let mut px = Vec::with_capacity(t.pixels() as usize);
                let mut chain = Vec::new();
                for y in t.y0..t.y1 {
                    for x in t.x0..t.x1 {
                        px.push(pixel(x, y, &mut chain, &mut st));
                    }
                }
                tick();
                (*t, px, st)
            })
            .collect()
    })
}

/// How a render in passes runs: `spp` samples a pixel (the mean with
/// adaptive sampling), stopping early at a noise target if there is one.
#[derive(Clone, Copy, Debug)]
struct InPasses {
    spp: u32,
    target: Option<f64>,
    adaptive: bool,
}

/// A render in passes: the whole image one pass at a time ([`passes`]),
/// each pixel's passes added in pass order as [`pixel_mean`] adds them (so
/// a render that runs every pass evenly is the same to the bit as one
/// that does not pass), until the estimate of the sums so far meets the
/// target ([`crate::metrics::meets_target`], which the farm's film asks at the same pass
/// ends) or `spp` is reached. With adaptive sampling, each pass after the
/// pilot gives its samples to the pixels by [`spread`], each pixel taking
/// the next indices of its own sequence. Returns the samples a pixel (the
/// mean, with adaptive sampling), the image's sums as one tile, and with
/// adaptive sampling each pixel's count.
fn render_in_passes(
    pool: &rayon::ThreadPool,
    tiles: &[Tile],
    kernel: &Kernel,
    tracer: &WholeScene,
    how: InPasses,
    tick: &(dyn Fn() + Sync),
) -> (u32, Vec<TileSums>, Option<Vec<u32>>) {
    let cam = kernel.camera;
    let (w, h) = (cam.width, cam.height);
    let pixels = w as usize * h as usize;
    let mut film = vec![PixelSum::default(); pixels];
    let mut counts = vec![0u32; pixels];
    let mut stats = TraceStats::default();
    let mut done = 0;
    let pilot = spread::pilot_end(how.spp);
    let cap = how.spp.saturating_mul(spread::MAX_SHARE);
    for pass in passes(how.spp) {
        // The samples each pixel takes in this pass: the pass's own, or
        // its samples spread by the pixels' noise so far.
        let given = if how.adaptive && pass.start >= pilot {
            let budget = pass.len() as u64 * pixels as u64;
            spread::spread(w, h, &film, &counts, budget, cap)
        } else {
            vec![pass.len() as u32; pixels]
        };
        let pixel = |x, y, chain: &mut _, st: &mut _| {
            let i = (y * w + x) as usize;
            let samples = counts[i]..counts[i] + given[i];
            PixelSum::from_total(pixel_pass(kernel, tracer, (x, y), samples, chain, st))
        };
        for (t, px, st) in render_tiles(pool, tiles, tick, pixel) {
            let mut px = px.iter();
            for y in t.y0..t.y1 {
                for x in t.x0..t.x1 {
                    let (i, p) = ((y * w + x) as usize, px.next().expect("a sum a pixel"));
                    if given[i] > 0 {
                        film[i].add_pass(p.total());
                        counts[i] += given[i];
                    }
                }
            }
            stats += st;
        }
        done = pass.end;
        let pixels_so_far = film.iter().zip(counts.iter().copied());
        if how
            .target
            .is_some_and(|t| meets_target_counted(pixels_so_far, done, t))
        {
            break;
        }
    }
    let whole = Tile {
        x0: 0,
        y0: 0,
        x1: w,
        y1: h,
    };
    let counts = how.adaptive.then_some(counts);
    (done, vec![(whole, film, stats)], counts)
}

/// The image, each pixel mean's variance (None for one sample a pixel)
/// and the counters, from the tiles' pixel sums, each pixel of `spp`
/// samples or of its own count in `counts`.
fn assemble(
    width: u32,
    height: u32,
    spp: u32,
    counts: Option<&[u32]>,
    results: Vec<TileSums>,
) -> (Image, Option<Image>, TraceStats) {
    let mut image = Image::new(width, height);
    let mut variance = (spp > 1).then(|| Image::new(width, height));
    let mut stats = TraceStats::default();
    for (t, px, st) in results {
        let mut sums = px.iter();
        for y in t.y0..t.y1 {
            for (x, p) in (t.x0..t.x1).zip(&mut sums) {
                let i = (y * width + x) as usize;
                let n = counts.map_or(spp, |c| c[i]);
                image.pixels[i] = p.mean(n);
                if let (Some(v), Some(var)) = (variance.as_mut(), p.variance_of_mean_f32(n)) {
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
