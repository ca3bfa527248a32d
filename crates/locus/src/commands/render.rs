//! `locus render`: on this machine, or on the embedded farm with
//! `--workers N`.

use crate::cli::*;
use crate::output::*;
use anyhow::{Context, Result};
use locus::config::Preset;
use locus_core::dircache::CacheParams;
use locus_core::image_io::Image;
use locus_core::irradiance::IrradianceParams;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::report::{PhaseTimes, RenderReport, SampleCounts};
use locus_core::sampler::Sampler;
use locus_core::scene::Scene;
use std::io::IsTerminal;
use std::path::Path;
use std::time::Instant;

pub(crate) fn progress_bar(total: u64, what: &str) -> Option<indicatif::ProgressBar> {
    if !std::io::stderr().is_terminal() {
        return None;
    }
    let pb = indicatif::ProgressBar::new(total);
    pb.set_style(
        indicatif::ProgressStyle::with_template(
            "{msg} [{bar:40}] {percent:>3}% {elapsed_precise} eta {eta}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    pb.set_message(what.to_string());
    Some(pb)
}

/// The preset and the caches `render` asks for.
pub(crate) struct Quality {
    pub(crate) preset: Option<Preset>,
    pub(crate) cache: Option<CacheParams>,
    pub(crate) irradiance: Option<IrradianceParams>,
}

/// The preset and the cache parameters `render` asks for.
pub(crate) fn render_quality(a: &RenderArgs) -> Result<Quality> {
    let preset = a.preset.as_deref().map(Preset::resolve).transpose()?;
    let cache = if a.cache {
        let mut c = preset.as_ref().map(|p| p.cache).unwrap_or_default();
        if let Some(r) = a.cache_radius {
            c.radius = r;
        }
        c.check()
            .map_err(|e| anyhow::anyhow!("--cache-radius: {e}"))?;
        Some(c)
    } else {
        None
    };
    let irradiance = if a.irradiance {
        let mut p = preset.as_ref().map(|p| p.irradiance).unwrap_or_default();
        if let Some(acc) = a.irradiance_accuracy {
            p.accuracy = acc;
        }
        p.check()
            .map_err(|e| anyhow::anyhow!("--irradiance-accuracy: {e}"))?;
        Some(p)
    } else {
        None
    };
    Ok(Quality {
        preset,
        cache,
        irradiance,
    })
}

pub(crate) fn cmd_render(a: RenderArgs) -> Result<()> {
    if a.workers > 0 {
        return cmd_render_farm(a);
    }
    // One machine, no memory budget: its BVH build reuses the blocks its
    // scratch frees (see "Build scratch kept for reuse" in
    // `docs/benchmarks/loading.md`).
    locus_worker::sys::reuse_freed_memory();
    super::limit_threads(a.threads);
    let t = Instant::now();
    let mut scene = Scene::load(&a.scene)?;
    let load_s = t.elapsed().as_secs_f64();
    tracing::info!(
        triangles = scene.tris.len(),
        dropped = scene.load_stats.degenerate_dropped,
        load_s,
        "scene loaded"
    );
    let mut opts = RenderOptions::from_scene(&scene);
    let Quality {
        preset,
        cache,
        irradiance,
    } = render_quality(&a)?;
    if let Some(p) = &preset {
        opts.spp = p.spp;
        opts.max_depth = p.max_depth;
    }
    opts.cache = cache;
    opts.irradiance = irradiance;
    if let Some(s) = a.spp {
        opts.spp = s.max(1);
    }
    if let Some(d) = a.max_depth {
        opts.max_depth = d;
    }
    if let Some(s) = a.seed {
        opts.seed = s;
    }
    if let Some(s) = a.sampler {
        opts.sampler = s;
    }
    if let Some(t) = a.target_rel_mse {
        opts.target_rel_mse = Some(t);
    }
    // The flag turns it on over a scene file that leaves it off.
    opts.adaptive |= a.adaptive_sampling;
    if let Some(b) = a.bvh {
        scene.settings.bvh = b;
    }
    opts.threads = a.threads;
    locus_core::limits::check_settings(opts.spp, opts.max_depth).map_err(anyhow::Error::msg)?;
    // The film and the image written from it.
    let cam = &scene.camera;
    locus_core::limits::check_film(cam.width, cam.height, 2, "this machine")
        .map_err(anyhow::Error::msg)?;
    // Read the reference before rendering so a bad path fails fast.
    let reference = a.reference.as_deref().map(Image::read_exr).transpose()?;
    // A job of few samples a triangle builds a quick BVH, as the farm's
    // workers do for the same job (unless its `bvh` setting says which).
    let prep = Prepared::for_job(scene, opts.spp);
    // What the build freed goes back to the system for the render.
    locus_worker::sys::trim_heap();
    tracing::info!(
        bvh_s = prep.timings.bvh_s,
        quality = ?prep.timings.quality,
        "acceleration built"
    );
    let (w, h) = (prep.scene.camera.width, prep.scene.camera.height);
    let ntiles = locus_core::render::tiles(w, h, opts.tile_size, opts.tile_order).len();
    let pb = progress_bar(ntiles as u64, "render");
    let out = render(&prep, &opts, &|done, total| {
        if let Some(pb) = &pb {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        }
    });
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    let Written {
        png,
        samples,
        json,
        error,
    } = write_image(
        &out.image,
        out.sample_counts.as_deref(),
        &a.output,
        a.exposure,
        reference.as_ref(),
    )?;
    let st = out.stats;
    let report = RenderReport {
        scene: a.scene.display().to_string(),
        image: a.output.display().to_string(),
        width: w,
        height: h,
        options: opts,
        threads_used: if opts.threads == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        } else {
            opts.threads
        },
        triangles: prep.scene.tris.len(),
        load: prep.scene.load_stats.clone(),
        octree_leaves: prep.octree_s().map(|_| prep.octree().leaf_count()),
        octree_references: prep.octree_s().map(|_| prep.octree().reference_count()),
        emitters: prep.lights.tris.len(),
        times: PhaseTimes {
            load_s,
            octree_s: prep.octree_s().unwrap_or(0.0),
            bvh_s: prep.timings.bvh_s,
            bvh_quality: prep.timings.quality,
            render_s: out.render_s,
        },
        stats: st,
        samples_per_second: st.samples as f64 / out.render_s,
        rays_per_second: st.rays() as f64 / out.render_s,
        error_vs_reference: error,
        error_estimate: out.error_estimate,
        spp_rendered: out.spp,
        sample_counts: out.sample_counts.as_deref().and_then(SampleCounts::of),
        cache_memory: out.cache_memory,
        irradiance: out.irradiance,
    };
    report
        .write(&json)
        .with_context(|| format!("writing {}", json.display()))?;
    if st.invalid_samples > 0 {
        tracing::warn!(
            invalid = st.invalid_samples,
            "non-finite samples were replaced by zero"
        );
    }
    println!(
        "wrote {} ({}x{}, {} spp) with {} and {}\n  load {:.3}s  octree {:.3}s  bvh {:.3}s{}  render {:.3}s  {:.0} samples/s  {:.2} Mrays/s",
        a.output.display(),
        w,
        h,
        out.spp,
        png.display(),
        json.display(),
        load_s,
        prep.octree_s().unwrap_or(0.0),
        prep.timings.bvh_s,
        prep.timings.quality.suffix(),
        out.render_s,
        report.samples_per_second,
        report.rays_per_second / 1e6
    );
    crate::output::print_sample_counts(report.sample_counts, samples.as_deref());
    if let (Some(m), c) = (out.cache_memory, st.cache) {
        println!(
            "  directional cache: {} local, {} global, {} lookups (hit ratio {:.1}%), {} nodes in {} leaves, {:.1} MiB",
            c.local,
            c.global,
            c.lookups,
            100.0 * c.hit_ratio(),
            m.nodes,
            m.leaves_with_cache,
            m.bytes as f64 / (1024.0 * 1024.0)
        );
    }
    if let Some(o) = out.irradiance {
        let u = st.irradiance;
        println!(
            "  irradiance cache: {} records from {} rays in {:.3}s ({:.1} MiB), {} first vertices interpolated, {} path traced",
            o.records,
            o.trace.rays(),
            o.seconds,
            o.bytes as f64 / (1024.0 * 1024.0),
            u.interpolated,
            u.traced
        );
    }
    crate::output::print_error(
        out.error_estimate.as_ref(),
        report.sample_counts,
        opts.sampler.name(),
        error.as_ref(),
    );
    crate::output::print_target(
        opts.target_rel_mse,
        out.error_estimate.as_ref(),
        out.spp,
        opts.spp,
    );
    Ok(())
}

/// What the command line sets over the scene file's `[render]`.
pub(crate) struct Overrides {
    pub(crate) spp: Option<u32>,
    pub(crate) max_depth: Option<u32>,
    pub(crate) seed: Option<u64>,
    pub(crate) sampler: Option<Sampler>,
    pub(crate) target_rel_mse: Option<f64>,
    /// Turns adaptive sampling on (a scene file may already have).
    pub(crate) adaptive_sampling: bool,
    pub(crate) bvh: Option<locus_core::accel::BvhSetting>,
}

pub(crate) fn load_for_farm(path: &Path, o: Overrides) -> Result<Scene> {
    let Overrides {
        spp,
        max_depth,
        seed,
        sampler,
        target_rel_mse,
        adaptive_sampling,
        bvh,
    } = o;
    let mut scene = Scene::load(path)?;
    if let Some(s) = spp {
        scene.settings.spp = s.max(1);
    }
    if let Some(d) = max_depth {
        scene.settings.max_depth = d;
    }
    if let Some(s) = seed {
        scene.settings.seed = s;
    }
    if let Some(s) = sampler {
        scene.settings.sampler = s;
    }
    if let Some(t) = target_rel_mse {
        scene.settings.target_rel_mse = Some(t);
    }
    scene.settings.adaptive_sampling |= adaptive_sampling;
    if let Some(b) = bvh {
        scene.settings.bvh = b;
    }
    let st = &scene.settings;
    locus_core::limits::check_settings(st.spp, st.max_depth).map_err(anyhow::Error::msg)?;
    // The client holds the image it receives.
    let cam = &scene.camera;
    locus_core::limits::check_film(cam.width, cam.height, 1, "this client")
        .map_err(anyhow::Error::msg)?;
    Ok(scene)
}

/// A bar fed by the farm's progress: pixel samples in the film, of all.
pub(crate) fn tile_progress(
    total_hint: u64,
) -> (Option<indicatif::ProgressBar>, impl Fn(u64, u64) + Sync) {
    let pb = progress_bar(total_hint, "farm");
    let pb2 = pb.clone();
    (pb, move |done: u64, total: u64| {
        if let Some(pb) = &pb2 {
            pb.set_length(total);
            pb.set_position(done);
        }
    })
}

pub(crate) fn cmd_render_farm(a: RenderArgs) -> Result<()> {
    let Quality {
        preset,
        cache,
        irradiance,
    } = render_quality(&a)?;
    let spp = a.spp.or(preset.as_ref().map(|p| p.spp));
    let depth = a.max_depth.or(preset.as_ref().map(|p| p.max_depth));
    let t = Instant::now();
    let scene = load_for_farm(
        &a.scene,
        Overrides {
            spp,
            max_depth: depth,
            seed: a.seed,
            sampler: a.sampler,
            target_rel_mse: a.target_rel_mse,
            adaptive_sampling: a.adaptive_sampling,
            bvh: a.bvh,
        },
    )?;
    let load_s = t.elapsed().as_secs_f64();
    let reference = a.reference.as_deref().map(Image::read_exr).transpose()?;
    let threads = if a.threads_per_worker > 0 {
        a.threads_per_worker
    } else {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        (cores / a.workers).max(1)
    };
    let mut opts = a.farm.job_options(a.workers as u32);
    opts.cache = cache;
    opts.irradiance = irradiance;
    // The scene's triangles move into the request: loaded once, not copied.
    let req = locus_scheduler::client::request_owned(scene, opts, load_s);
    let (pb, progress) = tile_progress(0);
    let spec = locus::farm::FarmSpec {
        http: a.http.clone(),
        ..locus::farm::FarmSpec::embedded(a.workers, threads)
    };
    let result = locus::farm::render_embedded(req, &spec, &progress)?;
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    write_farm_result(&a.scene, &a.output, a.exposure, &result, reference.as_ref())
}
