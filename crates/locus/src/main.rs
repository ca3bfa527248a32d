//! `locus`: the command line of the locus render farm.
//!
//! Subcommands: `render` (single machine for now; the farm arrives with the
//! scheduler and worker crates), `diff` (error metrics between two EXRs),
//! `gen` (writes generated scenes) and `bench` (tracing throughput).
//! Logs go to stderr through `tracing`, filtered by `RUST_LOG`.

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use locus_core::bench;
use locus_core::generate::{RoomParams, write_room};
use locus_core::image_io::Image;
use locus_core::metrics::compare;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::report::{PhaseTimes, RenderReport};
use locus_core::scene::Scene;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Parser)]
#[command(
    name = "locus",
    version,
    about = "Distributed global-illumination render farm"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Render a scene to EXR, with a PNG preview and a JSON report beside it.
    Render(RenderArgs),
    /// Error metrics (RMSE, relative MSE, MAE) between two EXR images.
    Diff { image: PathBuf, reference: PathBuf },
    /// Write a generated scene.
    Gen {
        #[command(subcommand)]
        what: GenWhat,
    },
    /// Measure BVH build, ray throughput against raw obvhs, and samples/s.
    Bench(BenchArgs),
}

#[derive(clap::Args)]
struct RenderArgs {
    scene: PathBuf,
    #[arg(short, long, default_value = "out.exr")]
    output: PathBuf,
    #[arg(long)]
    spp: Option<u32>,
    #[arg(long)]
    max_depth: Option<u32>,
    #[arg(long)]
    seed: Option<u64>,
    /// Compute threads (0: all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// A converged EXR to measure the error against.
    #[arg(long)]
    reference: Option<PathBuf>,
    /// Exposure multiplier for the PNG preview.
    #[arg(long, default_value_t = 1.0)]
    exposure: f32,
}

#[derive(Subcommand)]
enum GenWhat {
    /// The conference-like room (about 330k triangles by default).
    Room {
        #[arg(short, long, default_value = "scenes/generated")]
        out_dir: PathBuf,
        #[arg(long, default_value = "room")]
        name: String,
        #[arg(long)]
        chairs_per_side: Option<u32>,
        #[arg(long)]
        detail: Option<u32>,
    },
}

#[derive(clap::Args)]
struct BenchArgs {
    /// Scene to measure; default: the generated room (written to
    /// scenes/generated if missing).
    scene: Option<PathBuf>,
    #[arg(long, default_value_t = 500_000)]
    rays: usize,
    #[arg(long, default_value_t = 5)]
    rounds: usize,
    #[arg(long, default_value_t = 4)]
    spp: u32,
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Write the results as JSON here too.
    #[arg(long)]
    json: Option<PathBuf>,
}

fn main() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let r = match cli.cmd {
        Cmd::Render(a) => cmd_render(a),
        Cmd::Diff { image, reference } => cmd_diff(&image, &reference),
        Cmd::Gen { what } => cmd_gen(what),
        Cmd::Bench(a) => cmd_bench(a),
    };
    if let Err(e) = r {
        tracing::error!("{e:#}");
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn progress_bar(total: u64, what: &str) -> Option<indicatif::ProgressBar> {
    if !std::io::stderr().is_terminal() {
        return None;
    }
    let pb = indicatif::ProgressBar::new(total);
    pb.set_style(
        indicatif::ProgressStyle::with_template(
            "{msg} [{bar:40}] {pos}/{len} tiles {elapsed_precise} eta {eta}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    pb.set_message(what.to_string());
    Some(pb)
}

fn sibling(path: &Path, ext: &str) -> PathBuf {
    path.with_extension(ext)
}

fn cmd_render(a: RenderArgs) -> Result<()> {
    let t = Instant::now();
    let scene = Scene::load(&a.scene)?;
    let load_s = t.elapsed().as_secs_f64();
    tracing::info!(
        triangles = scene.tris.len(),
        dropped = scene.load_stats.degenerate_dropped,
        load_s,
        "scene loaded"
    );
    let mut opts = RenderOptions::from_scene(&scene);
    if let Some(s) = a.spp {
        opts.spp = s.max(1);
    }
    if let Some(d) = a.max_depth {
        opts.max_depth = d;
    }
    if let Some(s) = a.seed {
        opts.seed = s;
    }
    opts.threads = a.threads;
    // Read the reference before rendering so a bad path fails fast.
    let reference = match &a.reference {
        Some(p) => Some(Image::read_exr(p)?),
        None => None,
    };
    let prep = Prepared::new(scene);
    tracing::info!(
        leaves = prep.octree.leaf_count(),
        octree_s = prep.timings.octree_s,
        bvh_s = prep.timings.bvh_s,
        "acceleration built"
    );
    let (w, h) = (prep.scene.camera.width, prep.scene.camera.height);
    let ntiles = locus_core::render::tiles(w, h, opts.tile_size, opts.tile_order).len();
    let pb = progress_bar(ntiles as u64, "render");
    let out = render(&prep, &opts, &|done, _| {
        if let Some(pb) = &pb {
            pb.set_position(done as u64);
        }
    });
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    if let Some(dir) = a.output.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    out.image.write_exr(&a.output)?;
    let png = sibling(&a.output, "png");
    out.image.write_png(&png, a.exposure)?;
    let error = match &reference {
        Some(r) => Some(compare(&out.image, r)?),
        None => None,
    };
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
        octree_leaves: prep.octree.leaf_count(),
        octree_references: prep.octree.reference_count(),
        emitters: prep.lights.tris.len(),
        times: PhaseTimes {
            load_s,
            octree_s: prep.timings.octree_s,
            bvh_s: prep.timings.bvh_s,
            render_s: out.render_s,
        },
        stats: st,
        samples_per_second: st.samples as f64 / out.render_s,
        rays_per_second: st.rays() as f64 / out.render_s,
        error_vs_reference: error,
    };
    let json = sibling(&a.output, "json");
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
        "wrote {} ({}x{}, {} spp) with {} and {}\n  load {:.3}s  octree {:.3}s  bvh {:.3}s  render {:.3}s  {:.0} samples/s  {:.2} Mrays/s",
        a.output.display(),
        w,
        h,
        opts.spp,
        png.display(),
        json.display(),
        load_s,
        prep.timings.octree_s,
        prep.timings.bvh_s,
        out.render_s,
        report.samples_per_second,
        report.rays_per_second / 1e6
    );
    if let Some(e) = error {
        println!("error vs reference: {e}");
    }
    Ok(())
}

fn cmd_diff(a: &Path, b: &Path) -> Result<()> {
    let ia = Image::read_exr(a)?;
    let ib = Image::read_exr(b)?;
    let m = compare(&ia, &ib)?;
    println!("{m}");
    Ok(())
}

fn cmd_gen(what: GenWhat) -> Result<()> {
    match what {
        GenWhat::Room {
            out_dir,
            name,
            chairs_per_side,
            detail,
        } => {
            let mut p = RoomParams::default();
            if let Some(c) = chairs_per_side {
                p.chairs_per_side = c;
            }
            if let Some(d) = detail {
                p.detail = d.max(1);
            }
            let (path, n) = write_room(&out_dir, &name, &p)
                .with_context(|| format!("writing {}", out_dir.display()))?;
            println!("wrote {} ({n} triangles)", path.display());
        }
    }
    Ok(())
}

fn default_room() -> Result<PathBuf> {
    let path = Path::new("scenes/generated/room.toml");
    if !path.is_file() {
        let (p, n) = write_room(
            Path::new("scenes/generated"),
            "room",
            &RoomParams::default(),
        )?;
        tracing::info!(triangles = n, path = %p.display(), "generated the benchmark room");
    }
    Ok(path.to_path_buf())
}

fn cmd_bench(a: BenchArgs) -> Result<()> {
    let path = match a.scene {
        Some(p) => p,
        None => default_room()?,
    };
    let scene = Scene::load(&path)?;
    if scene.tris.is_empty() {
        bail!("{}: scene has no triangles", path.display());
    }
    let prep = Prepared::new(scene);
    let r = bench::run(&prep, a.rays, a.rounds, a.spp, a.threads);
    println!("scene {} ({} triangles)", path.display(), r.triangles);
    println!("BVH build (obvhs CWBVH, medium): {:.3} s", r.bvh_build_s);
    println!(
        "incoherent rays, 1 thread: locus {:.2} Mrays/s, raw obvhs {:.2} Mrays/s, overhead {:+.1}% ({} of {} closest hits agree)",
        r.locus_mrays_per_s,
        r.obvhs_mrays_per_s,
        r.overhead * 100.0,
        r.hits_agree,
        r.rays
    );
    println!(
        "path tracing: {:.0} samples/s ({} spp, {} threads)",
        r.samples_per_s, r.spp, r.threads
    );
    if let Some(j) = a.json {
        std::fs::write(&j, serde_json::to_string_pretty(&r)?)
            .with_context(|| format!("writing {}", j.display()))?;
    }
    Ok(())
}
