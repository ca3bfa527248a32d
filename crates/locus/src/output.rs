//! What a render writes, on one machine or on the farm alike: the EXR, its
//! PNG preview and the JSON report beside it (with adaptive sampling, the
//! samples each pixel got as an EXR too), and the summary printed.

use anyhow::{Context, Result};
use locus_core::image_io::Image;
use locus_core::metrics::{ErrorEstimate, ErrorMetrics, compare};
use locus_protocol::report::FarmReport;
use locus_protocol::submit::{FetchPolicy, JobResult};
use std::path::{Path, PathBuf};

/// What [`write_image`] wrote, and the error against the reference.
pub(crate) struct Written {
    pub(crate) png: PathBuf,
    /// With adaptive sampling, the samples each pixel got, as an EXR.
    pub(crate) samples: Option<PathBuf>,
    /// Where the caller's JSON report goes.
    pub(crate) json: PathBuf,
    pub(crate) error: Option<ErrorMetrics>,
}

/// Writes `image` as the EXR `output` (creating its folder) and its sRGB
/// PNG preview beside it, with adaptive sampling each pixel's count as
/// `NAME.samples.exr` (the count in every channel), and measures it against
/// `reference`: the one writer of both one machine's and the farm's images.
pub(crate) fn write_image(
    image: &Image,
    counts: Option<&[u32]>,
    output: &Path,
    exposure: f32,
    reference: Option<&Image>,
) -> Result<Written> {
    if let Some(dir) = output.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    image.write_exr(output)?;
    let png = sibling(output, "png");
    image.write_png(&png, exposure)?;
    let samples = match counts {
        Some(c) => {
            let path = sibling(output, "samples.exr");
            let mut img = Image::new(image.width, image.height);
            for (p, &n) in img.pixels.iter_mut().zip(c) {
                *p = [n as f32; 3];
            }
            img.write_exr(&path)?;
            Some(path)
        }
        None => None,
    };
    let error = match reference {
        Some(re) => Some(compare(image, re)?),
        None => None,
    };
    Ok(Written {
        png,
        samples,
        json: sibling(output, "json"),
        error,
    })
}

pub(crate) fn sibling(path: &Path, ext: &str) -> PathBuf {
    path.with_extension(ext)
}

/// The JSON a farm render writes beside its EXR.
#[derive(serde::Serialize)]
pub(crate) struct FarmOutput<'a> {
    pub(crate) scene: String,
    pub(crate) image: String,
    pub(crate) farm: &'a FarmReport,
    pub(crate) error_vs_reference: Option<locus_core::metrics::ErrorMetrics>,
}

/// A farm job's image.
pub(crate) fn image_of(r: &JobResult) -> Image {
    Image {
        width: r.width,
        height: r.height,
        pixels: r.pixels.clone(),
    }
}

pub(crate) fn write_farm_result(
    scene: &Path,
    output: &Path,
    exposure: f32,
    r: &JobResult,
    reference: Option<&Image>,
) -> Result<()> {
    let Written {
        png,
        samples,
        json,
        error,
    } = write_image(
        &image_of(r),
        r.sample_counts.as_deref(),
        output,
        exposure,
        reference,
    )?;
    let out = FarmOutput {
        scene: scene.display().to_string(),
        image: output.display().to_string(),
        farm: &r.report,
        error_vs_reference: error,
    };
    std::fs::write(&json, serde_json::to_string_pretty(&out)?)
        .with_context(|| format!("writing {}", json.display()))?;
    let f = &r.report;
    println!(
        "wrote {} ({}x{}, {} spp, {} workers, {}) with {} and {}",
        output.display(),
        r.width,
        r.height,
        f.spp_rendered,
        f.workers.len(),
        f.partitioner,
        png.display(),
        json.display()
    );
    // Every fixed cost, so that none hides in the total: the preview can
    // take longer than the partition it feeds by a factor of twenty.
    let ph = &f.phases;
    let layout = match ph.layout_s > 0.0 {
        true => format!(", layout at the scheduler {:.3}s", ph.layout_s),
        false => String::new(),
    };
    println!(
        "  load {:.3}s  octree {:.3}s  preview {:.3}s  partition {:.3}s  distribution {:.3}s (bvh {:.3}s{}{layout})  render {:.3}s  total {:.3}s  {:.0} samples/s",
        ph.load_s,
        ph.octree_s,
        ph.preview_s,
        ph.partition_s,
        ph.distribution_s,
        ph.bvh_s,
        f.bvh_quality.suffix(),
        ph.render_s,
        ph.total_s,
        f.samples_per_s
    );
    let r = match (f.prediction.analytic_r, f.prediction.sampled_r) {
        (Some(a), Some(s)) => format!("  prediction r: analytic {a:.2}, sampled {s:.2}"),
        _ => String::new(),
    };
    println!(
        "  load imbalance {:.3} ({:.3} with setup)  forwarded per ray {:.3}  bytes per sample {:.1}{r}",
        f.load_imbalance, f.total_imbalance, f.forwarded_fraction, f.bytes_per_sample,
    );
    if f.replicated {
        let why = if f.policy == FetchPolicy::Adaptive.name() {
            "it fit, and its rays would have cost more than its geometry"
        } else {
            "it fit every worker's memory plan"
        };
        println!("  {}: every worker held the whole scene ({why})", f.policy);
    } else if f.shared_leaves > 0 {
        println!(
            "  shared: every worker held {} leaves ({} triangle references; the scene has {} triangles) beside its region",
            f.shared_leaves, f.shared_refs, f.triangles
        );
    }
    let k = &f.totals.forwards;
    if k.total() > 0 {
        let predicted = f.prediction.forwards_per_path.map_or(String::new(), |p| {
            format!(" (the preview predicted {p:.3})")
        });
        let [b1, b2, b3, b4] = k.bounces;
        println!(
            "  forwarded {} queries, {:.3} a sample{predicted}: camera rays {}, bounces after 1 / 2 / 3 / 4+ vertices {b1} / {b2} / {b3} / {b4}, shadow rays {}",
            k.total(),
            k.total() as f64 / f.totals.trace.samples.max(1) as f64,
            k.camera,
            k.shadow
        );
    }
    if f.totals.shared_parts > 0 {
        println!(
            "  BVH parts built once for this process's workers: {} taken from another worker's build",
            f.totals.shared_parts
        );
    }
    if f.totals.shipped_layouts > 0 {
        println!(
            "  BVH laid out once by the scheduler: {} workers took its layout rather than building",
            f.totals.shipped_layouts
        );
    }
    let t = &f.totals;
    let c = t.trace.cache;
    if c.local + c.global + c.lookups > 0 {
        println!(
            "  directional caches: {} local, {} global, {} lookups (hit ratio {:.1}%), {} nodes in {} leaves, {:.1} MiB",
            c.local,
            c.global,
            c.lookups,
            100.0 * c.hit_ratio(),
            t.cache_memory.nodes,
            t.cache_memory.leaves_with_cache,
            t.cache_memory.bytes as f64 / (1024.0 * 1024.0)
        );
    }
    if let Some(o) = &f.irradiance {
        let u = t.trace.irradiance;
        let by = if o.by_workers {
            "measured by the workers"
        } else {
            "measured on the scheduler"
        };
        println!(
            "  irradiance cache: {} records from {} rays in {:.3}s {by}, {:.2} MB gathered from and {:.2} MB sent to the workers; {} first vertices interpolated, {} path traced",
            o.records,
            o.rays,
            o.seconds,
            o.bytes_gathered as f64 / 1e6,
            o.bytes_sent as f64 / 1e6,
            u.interpolated,
            u.traced
        );
    }
    if t.fetch_requests > 0 {
        println!(
            "  fetched {} leaves ({:.2} MB on the wire) for {} waiting rays; {} crossings of fetched leaves; store peak {:.1} of {:.1} MiB per worker",
            t.fetched_leaves,
            t.fetched_bytes as f64 / 1e6,
            t.fetch_waits,
            t.fetched_leaf_traces,
            t.fetch_cache_peak as f64 / (1024.0 * 1024.0),
            t.fetch_cache_bound as f64 / (1024.0 * 1024.0)
        );
    }
    println!(
        "  worker  leaves  triangles  rays-local  fwd-out  queries-in  MB-sent  busy-s  idle-s  pred%  meas%"
    );
    for w in &f.workers {
        let s = &w.stats;
        let sent: u64 = s.peers.iter().map(|p| p.bytes_sent).sum();
        // A replica holds every leaf, whatever its processor map names.
        let leaves = if f.replicated { f.leaves } else { s.leaves };
        println!(
            "  {:>6}  {:>6}  {:>9}  {:>10}  {:>7}  {:>10}  {:>7.2}  {:>6.2}  {:>6.2}  {:>5.1}  {:>5.1}",
            w.id,
            leaves,
            s.triangles,
            s.trace.bvh_queries,
            s.forwarded_out,
            s.queries_in,
            sent as f64 / 1e6,
            s.busy_s,
            s.idle_s,
            w.predicted_cost_share * 100.0,
            w.measured_cost_share * 100.0
        );
    }
    print_sample_counts(f.sample_counts, samples.as_deref());
    print_error(
        f.error_estimate.as_ref(),
        f.sample_counts,
        &f.sampler,
        error.as_ref(),
    );
    print_target(
        f.target_rel_mse,
        f.error_estimate.as_ref(),
        f.spp_rendered,
        f.spp,
    );
    Ok(())
}

/// The error a rendered image carries: as its samples' spread gives it,
/// and against the reference when one was given.
pub(crate) fn print_error(
    estimate: Option<&ErrorEstimate>,
    counts: Option<locus_core::report::SampleCounts>,
    sampler: &str,
    reference: Option<&ErrorMetrics>,
) {
    if let Some(e) = estimate {
        // The spread is the error of independent samples; Sobol's are
        // stratified (`locus bench quality` on the Cornell box: the true
        // relMSE 0.65 of the estimate at 16 spp, 0.49 at 64, 0.43 at 256).
        let note = if sampler == locus_core::sampler::Sampler::Sobol.name() {
            "; an upper estimate with the Sobol sampler, whose stratified samples usually leave less"
        } else {
            ""
        };
        // An adaptive render's pixels each have their own count.
        let e = match counts {
            Some(c) => e.read_from(&format!(
                "{} to {} samples a pixel, {:.2} on average",
                c.min, c.max, c.mean
            )),
            None => e.to_string(),
        };
        println!("estimated error: {e}{note}");
    }
    if let Some(e) = reference {
        println!("error vs reference: {e}");
    }
}

/// With adaptive sampling, the spread of the samples over the pixels, and
/// the image of them.
pub(crate) fn print_sample_counts(
    counts: Option<locus_core::report::SampleCounts>,
    image: Option<&Path>,
) {
    if let (Some(c), Some(image)) = (counts, image) {
        println!(
            "  adaptive sampling: {} to {} samples a pixel, {:.2} on average ({})",
            c.min,
            c.max,
            c.mean,
            image.display()
        );
    }
}

/// Says whether a render with a noise target met it (its final estimate is
/// the one the last pass was judged by), at `rendered` samples a pixel of
/// at most `spp`.
pub(crate) fn print_target(
    target: Option<f64>,
    estimate: Option<&ErrorEstimate>,
    rendered: u32,
    spp: u32,
) {
    let Some(t) = target else { return };
    if estimate.is_some_and(|e| e.rel_mse <= t) {
        println!("noise target {t:.3e} met after {rendered} of at most {spp} spp");
    } else {
        println!("noise target {t:.3e} not met within {spp} spp: raise --spp to go on");
    }
}
