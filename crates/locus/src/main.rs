//! `locus`: the command line of the locus render farm.
//!
//! Subcommands: `render` (single machine, or the embedded farm with
//! `--workers N`), the daemons `scheduler` and `worker`, `submit` (a job to a
//! running farm), `diff` (error metrics between two EXRs), `gen` (writes
//! generated scenes) and `bench` (tracing throughput; `bench farm` for the
//! farm). Logs go to stderr through `tracing`, filtered by `RUST_LOG`.

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use locus::config::{Config, Preset};
use locus_core::bench;
use locus_core::dircache::CacheParams;
use locus_core::generate::{RoomParams, write_room};
use locus_core::image_io::Image;
use locus_core::metrics::compare;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::report::{PhaseTimes, RenderReport};
use locus_core::scene::Scene;
use locus_protocol::control::Tuning;
use locus_protocol::report::FarmReport;
use locus_protocol::submit::{CostModel, FetchPolicy, JobOptions, JobResult, Partitioner};
use locus_scheduler::{Scheduler, SchedulerConfig};
use locus_worker::{Worker, WorkerConfig};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tokio_util::sync::CancellationToken;

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
    /// Run the scheduler daemon.
    Scheduler(SchedulerArgs),
    /// Run a worker daemon.
    Worker(WorkerArgs),
    /// Submit a scene to a running farm and write the result.
    Submit(SubmitArgs),
    /// The farm benchmark: overhead against one machine, speedup, and
    /// region growing against the Morton baseline for 2, 4 and 8 workers.
    BenchFarm(BenchFarmArgs),
}

#[derive(clap::Args)]
struct BenchFarmArgs {
    /// Scenes to measure; default: the generated room, and the conference
    /// room where ../shared has its mesh.
    scenes: Vec<PathBuf>,
    #[arg(long, default_value_t = 320)]
    width: u32,
    #[arg(long, default_value_t = 240)]
    height: u32,
    #[arg(long, default_value_t = 16)]
    spp: u32,
    /// Runs per configuration; the fastest is reported (shared machines
    /// are noisy, and noise only ever adds time).
    #[arg(long, default_value_t = 1)]
    repeat: u32,
    /// Farm sizes to measure.
    #[arg(long, num_args = 1.., default_values_t = [1usize, 2, 4, 8])]
    workers: Vec<usize>,
    #[arg(long, num_args = 1.., default_values = ["forward", "fetch", "adaptive"])]
    policies: Vec<FetchPolicy>,
    /// Cores one machine uses and the farms share (0: all of them).
    #[arg(long, default_value_t = 0)]
    cores: usize,
    /// Each of the 4 workers' memory budget for the large scene.
    #[arg(long, default_value = "160M")]
    large_budget: locus::config::ByteSize,
    /// Leave out the large generated scene (4 million triangles).
    #[arg(long, conflicts_with = "large_only")]
    no_large: bool,
    /// Measure only the large generated scene.
    #[arg(long)]
    large_only: bool,
    /// Write the rows as JSON here too.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Write the Markdown tables here too.
    #[arg(long)]
    markdown: Option<PathBuf>,
}

#[derive(clap::Args, Clone)]
struct TokenArgs {
    /// Shared cluster token (or LOCUS_TOKEN, or `token` in --config).
    #[arg(long, env = "LOCUS_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// A TOML config file (see configs/).
    #[arg(long)]
    config: Option<PathBuf>,
}

#[derive(clap::Args)]
struct SchedulerArgs {
    /// host:port to listen on (port 0 picks one and logs it).
    #[arg(long)]
    listen: Option<String>,
    #[command(flatten)]
    auth: TokenArgs,
}

#[derive(clap::Args)]
struct WorkerArgs {
    /// The scheduler's host:port.
    #[arg(long)]
    scheduler: Option<String>,
    /// host:port for peer links (port 0 picks one).
    #[arg(long)]
    listen: Option<String>,
    /// Address peers should dial, if not the bound one.
    #[arg(long)]
    advertise: Option<String>,
    /// Tracing threads (0: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Memory this worker's process may use, e.g. 4G (default: no limit):
    /// the scheduler gives it no more of the scene than fits, and it
    /// builds and fetches within it.
    #[arg(long)]
    memory_budget: Option<locus::config::ByteSize>,
    #[command(flatten)]
    auth: TokenArgs,
}

#[derive(clap::Args, Clone)]
struct FarmArgs {
    /// Partitioner of octree leaves into regions.
    #[arg(long, value_enum, default_value = "region-growing")]
    partitioner: PartitionerArg,
    /// Leaf cost prediction the partitioner balances.
    #[arg(long, value_enum, default_value = "sampled")]
    cost: CostArg,
    /// Most ray items per packet (a packet also leaves when its worker
    /// runs out of work).
    #[arg(long, default_value_t = 1024)]
    packet_size: u32,
    /// Flush deadline of a partly filled packet while its worker is busy,
    /// in microseconds.
    #[arg(long, default_value_t = 1000)]
    flush_us: u32,
    /// Camera samples each worker keeps in flight.
    #[arg(long, default_value_t = 65536)]
    max_inflight: u32,
    #[arg(long, default_value_t = 16)]
    tile_size: u32,
    /// What a worker does with a ray reaching another worker's leaf:
    /// forward it, fetch the leaf's geometry, hybrid or adaptive (rent or
    /// buy: the whole scene at the start when that pays and fits, else
    /// leaf by leaf).
    #[arg(long, default_value = "adaptive")]
    fetch: FetchPolicy,
    /// MiB of fetched geometry each worker keeps (LRU-like eviction).
    #[arg(long, default_value_t = 256)]
    fetch_budget_mib: u64,
}

#[derive(clap::ValueEnum, Clone, Copy)]
enum PartitionerArg {
    RegionGrowing,
    Morton,
}

#[derive(clap::ValueEnum, Clone, Copy)]
enum CostArg {
    Analytic,
    Sampled,
}

#[derive(clap::Args)]
struct SubmitArgs {
    scene: PathBuf,
    /// The scheduler's host:port.
    #[arg(long)]
    scheduler: Option<String>,
    #[arg(short, long, default_value = "out.exr")]
    output: PathBuf,
    /// Workers to use (0: every registered worker).
    #[arg(long, default_value_t = 0)]
    workers: u32,
    #[arg(long)]
    spp: Option<u32>,
    #[arg(long)]
    max_depth: Option<u32>,
    #[arg(long)]
    seed: Option<u64>,
    #[arg(long)]
    reference: Option<PathBuf>,
    #[arg(long, default_value_t = 1.0)]
    exposure: f32,
    #[command(flatten)]
    farm: FarmArgs,
    #[command(flatten)]
    auth: TokenArgs,
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
    /// Render on the embedded farm with this many workers (scheduler and
    /// workers in this process, linked over loopback TCP); 0 renders on
    /// this machine without the farm.
    #[arg(long, default_value_t = 0)]
    workers: usize,
    /// Tracing threads per embedded worker (0: cores / workers, at least 1).
    #[arg(long, default_value_t = 0)]
    threads_per_worker: usize,
    /// A quality preset (configs/presets/*.toml): spp, depth and the
    /// directional cache's parameters; --spp and --max-depth override it.
    #[arg(long)]
    preset: Option<PathBuf>,
    /// Switch the directional cache on (the preset's parameters, or the
    /// defaults); direct light is then estimated by light sampling alone.
    #[arg(long)]
    cache: bool,
    /// Locality radius in leaf edges (overrides the preset's).
    #[arg(long)]
    cache_radius: Option<f32>,
    #[command(flatten)]
    farm: FarmArgs,
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
#[command(args_conflicts_with_subcommands = true)]
struct BenchArgs {
    #[command(subcommand)]
    what: Option<BenchWhat>,
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

#[derive(Subcommand)]
enum BenchWhat {
    /// Paper 000's Tables 1-3: every preset with and without the
    /// directional cache, under every fetch policy, on the embedded farm,
    /// against a converged reference; writes locality.md, .csv and .svg.
    Locality(LocalityArgs),
}

#[derive(clap::Args)]
struct LocalityArgs {
    scene: PathBuf,
    #[arg(long, default_value_t = 4)]
    workers: usize,
    /// Tracing threads per worker (0: cores / workers, at least 1).
    #[arg(long, default_value_t = 0)]
    threads_per_worker: usize,
    #[arg(long, default_value_t = 160)]
    width: u32,
    #[arg(long, default_value_t = 120)]
    height: u32,
    /// Samples per pixel of the converged reference (MIS, no cache).
    #[arg(long, default_value_t = 1024)]
    reference_spp: u32,
    /// Preset files; default: configs/presets/{accurate,fast,low}.toml.
    #[arg(long, num_args = 1..)]
    presets: Vec<PathBuf>,
    /// Policies to measure.
    #[arg(long, num_args = 1.., default_values = ["forward", "fetch", "hybrid", "adaptive"])]
    policies: Vec<FetchPolicy>,
    #[arg(long, default_value_t = 256)]
    fetch_budget_mib: u64,
    /// Where the tables, the plot and the reference go; default
    /// bench-out/locality-<scene>.
    #[arg(long)]
    out_dir: Option<PathBuf>,
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
        Cmd::Scheduler(a) => cmd_scheduler(a),
        Cmd::Worker(a) => cmd_worker(a),
        Cmd::Submit(a) => cmd_submit(a),
        Cmd::BenchFarm(a) => cmd_bench_farm(a),
    };
    if let Err(e) = r {
        let msg = error_chain(&e);
        tracing::error!("{msg}");
        eprintln!("error: {msg}");
        std::process::exit(1);
    }
}

/// An error and its causes, each cause once: our error types already name
/// their source in their own message, and a cause repeated after it reads
/// like a second failure.
fn error_chain(e: &anyhow::Error) -> String {
    let mut msg = String::new();
    for cause in e.chain() {
        let s = cause.to_string();
        if !msg.contains(&s) {
            if !msg.is_empty() {
                msg.push_str(": ");
            }
            msg.push_str(&s);
        }
    }
    msg
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

/// The preset and the directional cache parameters `render` asks for.
fn render_quality(a: &RenderArgs) -> Result<(Option<Preset>, Option<CacheParams>)> {
    let preset = a.preset.as_deref().map(Preset::load).transpose()?;
    if !a.cache {
        return Ok((preset, None));
    }
    let mut c = preset.as_ref().map(|p| p.cache).unwrap_or_default();
    if let Some(r) = a.cache_radius {
        c.radius = r;
    }
    c.check()
        .map_err(|e| anyhow::anyhow!("--cache-radius: {e}"))?;
    Ok((preset, Some(c)))
}

fn cmd_render(a: RenderArgs) -> Result<()> {
    if a.workers > 0 {
        return cmd_render_farm(a);
    }
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
    let (preset, cache) = render_quality(&a)?;
    if let Some(p) = &preset {
        opts.spp = p.spp;
        opts.max_depth = p.max_depth;
    }
    opts.cache = cache;
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
    tracing::info!(bvh_s = prep.timings.bvh_s, "acceleration built");
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
        octree_leaves: prep.octree_s().map(|_| prep.octree().leaf_count()),
        octree_references: prep.octree_s().map(|_| prep.octree().reference_count()),
        emitters: prep.lights.tris.len(),
        times: PhaseTimes {
            load_s,
            octree_s: prep.octree_s().unwrap_or(0.0),
            bvh_s: prep.timings.bvh_s,
            render_s: out.render_s,
        },
        stats: st,
        samples_per_second: st.samples as f64 / out.render_s,
        rays_per_second: st.rays() as f64 / out.render_s,
        error_vs_reference: error,
        cache_memory: out.cache_memory,
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
        prep.octree_s().unwrap_or(0.0),
        prep.timings.bvh_s,
        out.render_s,
        report.samples_per_second,
        report.rays_per_second / 1e6
    );
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

fn cmd_bench_locality(a: LocalityArgs) -> Result<()> {
    if a.scene == Path::new("scenes/generated/room.toml") {
        default_room()?;
    }
    let stem = a
        .scene
        .file_stem()
        .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
    let presets = if a.presets.is_empty() {
        ["accurate", "fast", "low"]
            .iter()
            .map(|n| PathBuf::from(format!("configs/presets/{n}.toml")))
            .collect()
    } else {
        a.presets
    };
    let workers = a.workers.max(1);
    let threads = if a.threads_per_worker > 0 {
        a.threads_per_worker
    } else {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        (cores / workers).max(1)
    };
    let plan = locus::locality::Plan {
        out_dir: a
            .out_dir
            .unwrap_or_else(|| PathBuf::from(format!("bench-out/locality-{stem}"))),
        scene: a.scene,
        width: a.width,
        height: a.height,
        workers,
        threads_per_worker: threads,
        reference_spp: a.reference_spp.max(1),
        presets,
        policies: a.policies,
        fetch_budget: a.fetch_budget_mib << 20,
    };
    locus::locality::run(&plan)?;
    let md = plan.out_dir.join("locality.md");
    print!(
        "{}",
        std::fs::read_to_string(&md).with_context(|| format!("reading {}", md.display()))?
    );
    println!("\nwrote {}, locality.csv and locality.svg", md.display());
    Ok(())
}

fn cmd_bench(a: BenchArgs) -> Result<()> {
    if let Some(BenchWhat::Locality(l)) = a.what {
        return cmd_bench_locality(l);
    }
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

fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?)
}

impl FarmArgs {
    fn job_options(&self, workers: u32) -> JobOptions {
        JobOptions {
            workers,
            partitioner: match self.partitioner {
                PartitionerArg::RegionGrowing => Partitioner::RegionGrowing,
                PartitionerArg::Morton => Partitioner::Morton,
            },
            cost_model: match self.cost {
                CostArg::Analytic => CostModel::Analytic,
                CostArg::Sampled => CostModel::Sampled,
            },
            tile_size: self.tile_size.max(1),
            tuning: Tuning {
                packet_size: self.packet_size.max(1),
                flush_us: self.flush_us,
                max_inflight: self.max_inflight.max(1),
                ..Tuning::default()
            },
            cache: None,
            fetch: self.fetch,
            fetch_budget: self.fetch_budget_mib << 20,
        }
    }
}

fn load_for_farm(
    path: &Path,
    spp: Option<u32>,
    max_depth: Option<u32>,
    seed: Option<u64>,
) -> Result<Scene> {
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
    Ok(scene)
}

fn tile_progress(total_hint: u64) -> (Option<indicatif::ProgressBar>, impl Fn(u32, u32) + Sync) {
    let pb = progress_bar(total_hint, "farm");
    let pb2 = pb.clone();
    (pb, move |done: u32, total: u32| {
        if let Some(pb) = &pb2 {
            pb.set_length(total as u64);
            pb.set_position(done as u64);
        }
    })
}

fn cmd_render_farm(a: RenderArgs) -> Result<()> {
    let (preset, cache) = render_quality(&a)?;
    let spp = a.spp.or(preset.as_ref().map(|p| p.spp));
    let depth = a.max_depth.or(preset.as_ref().map(|p| p.max_depth));
    let scene = load_for_farm(&a.scene, spp, depth, a.seed)?;
    let reference = match &a.reference {
        Some(p) => Some(Image::read_exr(p)?),
        None => None,
    };
    let threads = if a.threads_per_worker > 0 {
        a.threads_per_worker
    } else {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        (cores / a.workers).max(1)
    };
    let mut opts = a.farm.job_options(a.workers as u32);
    opts.cache = cache;
    let req = locus_scheduler::client::request(&scene, opts);
    let (pb, progress) = tile_progress(0);
    let result = locus::farm::render_embedded(req, a.workers, threads, &progress)?;
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    write_farm_result(&a.scene, &a.output, a.exposure, &result, reference.as_ref())
}

/// The JSON a farm render writes beside its EXR.
#[derive(serde::Serialize)]
struct FarmOutput<'a> {
    scene: String,
    image: String,
    farm: &'a FarmReport,
    error_vs_reference: Option<locus_core::metrics::ErrorMetrics>,
}

fn write_farm_result(
    scene: &Path,
    output: &Path,
    exposure: f32,
    r: &JobResult,
    reference: Option<&Image>,
) -> Result<()> {
    let image = Image {
        width: r.width,
        height: r.height,
        pixels: r.pixels.clone(),
    };
    if let Some(dir) = output.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    image.write_exr(output)?;
    let png = sibling(output, "png");
    image.write_png(&png, exposure)?;
    let error = match reference {
        Some(re) => Some(compare(&image, re)?),
        None => None,
    };
    let json = sibling(output, "json");
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
        f.spp,
        f.workers.len(),
        f.partitioner,
        png.display(),
        json.display()
    );
    println!(
        "  partition {:.3}s  distribution {:.3}s  render {:.3}s  {:.0} samples/s",
        f.phases.partition_s, f.phases.distribution_s, f.phases.render_s, f.samples_per_s
    );
    println!(
        "  load imbalance {:.3}  forwarded per ray {:.3}  bytes per sample {:.1}  prediction r: analytic {:.2}, sampled {:.2}",
        f.load_imbalance,
        f.forwarded_fraction,
        f.bytes_per_sample,
        f.prediction.analytic_r,
        f.prediction.sampled_r
    );
    if f.replicated {
        let why = if f.policy == FetchPolicy::Adaptive.name() {
            "it fit, and its rays would have cost more than its geometry"
        } else {
            "it fit every worker's memory plan"
        };
        println!("  {}: every worker held the whole scene ({why})", f.policy);
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
        println!(
            "  {:>6}  {:>6}  {:>9}  {:>10}  {:>7}  {:>10}  {:>7.2}  {:>6.2}  {:>6.2}  {:>5.1}  {:>5.1}",
            w.id,
            s.leaves,
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
    if let Some(e) = error {
        println!("error vs reference: {e}");
    }
    Ok(())
}

fn cmd_scheduler(a: SchedulerArgs) -> Result<()> {
    let cfg = Config::load(a.auth.config.as_deref())?;
    let token = cfg.token(a.auth.token.clone(), a.auth.config.as_ref())?;
    let listen = a
        .listen
        .or(cfg.scheduler.listen.clone())
        .context("no listen address: pass --listen or set [scheduler] listen in the config")?;
    runtime()?.block_on(async {
        let s = Scheduler::bind(SchedulerConfig {
            listen,
            token,
            max_queued_jobs: cfg.scheduler.max_queued_jobs.unwrap_or(16),
        })
        .await?;
        serve("scheduler", s.local_addr()?, |t| s.run(t)).await
    })
}

/// Prints the bound address (scripts read it from this line) and runs a
/// daemon until SIGINT or SIGTERM.
async fn serve<F: std::future::Future<Output = Result<()>>>(
    what: &str,
    addr: std::net::SocketAddr,
    run: impl FnOnce(CancellationToken) -> F,
) -> Result<()> {
    println!("{what} listening on {addr}");
    let shutdown = CancellationToken::new();
    locus::cancel_on_signals(shutdown.clone());
    run(shutdown).await
}

fn cmd_worker(a: WorkerArgs) -> Result<()> {
    let cfg = Config::load(a.auth.config.as_deref())?;
    let token = cfg.token(a.auth.token.clone(), a.auth.config.as_ref())?;
    let w = &cfg.worker;
    let scheduler = a.scheduler.or(w.scheduler.clone()).context(
        "no scheduler address: pass --scheduler or set [worker] scheduler in the config",
    )?;
    let listen = a
        .listen
        .or(w.listen.clone())
        .context("no listen address: pass --listen or set [worker] listen in the config")?;
    let wc = WorkerConfig {
        scheduler,
        listen,
        advertise: a.advertise.or(w.advertise.clone()),
        token,
        threads: a.threads.or(w.threads).unwrap_or(0),
        memory_budget: a.memory_budget.or(w.memory_budget).map_or(0, |b| b.0),
        name: w
            .name
            .clone()
            .unwrap_or_else(|| format!("worker-{}", std::process::id())),
        dedicated: true,
    };
    if wc.memory_budget > 0 {
        locus_worker::sys::tune_allocator();
    }
    runtime()?.block_on(async {
        let worker = Worker::bind(wc).await?;
        serve("worker", worker.local_addr()?, |t| worker.run(t)).await
    })
}

fn cmd_submit(a: SubmitArgs) -> Result<()> {
    let cfg = Config::load(a.auth.config.as_deref())?;
    let token = cfg.token(a.auth.token.clone(), a.auth.config.as_ref())?;
    let scheduler = a
        .scheduler
        .clone()
        .or(cfg.worker.scheduler.clone())
        .context(
            "no scheduler address: pass --scheduler or set [worker] scheduler in the config",
        )?;
    let scene = load_for_farm(&a.scene, a.spp, a.max_depth, a.seed)?;
    let reference = match &a.reference {
        Some(p) => Some(Image::read_exr(p)?),
        None => None,
    };
    let req = locus_scheduler::client::request(&scene, a.farm.job_options(a.workers));
    let (pb, progress) = tile_progress(0);
    let result = runtime()?.block_on(async {
        let shutdown = CancellationToken::new();
        locus::cancel_on_signals(shutdown.clone());
        tokio::select! {
            r = locus_scheduler::client::submit(&scheduler, &token, req, &progress) => r,
            _ = shutdown.cancelled() => Err(anyhow::anyhow!("interrupted")),
        }
    })?;
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    write_farm_result(&a.scene, &a.output, a.exposure, &result, reference.as_ref())
}

fn cmd_bench_farm(a: BenchFarmArgs) -> Result<()> {
    let mut scenes = if a.large_only {
        Vec::new()
    } else if a.scenes.is_empty() {
        let mut v = vec![default_room()?];
        // The conference room's mesh lives beside a checkout (see its
        // scene file); it is measured where it is there.
        let conf = Path::new("scenes/conference/conference.toml");
        if Path::new("../shared/scenes/conference/conference.obj").is_file() && conf.is_file() {
            v.push(conf.to_path_buf());
        }
        v
    } else {
        a.scenes.clone()
    };
    for s in &mut scenes {
        if s == Path::new("scenes/generated/room.toml") {
            *s = default_room()?;
        }
    }
    let cores = if a.cores > 0 {
        a.cores
    } else {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    };
    let large = if a.no_large {
        None
    } else {
        Some(locus::bench_farm::Large {
            path: locus::bench_farm::large_scene(Path::new("scenes/generated"))?,
            workers: 4,
            budget: a.large_budget.0,
        })
    };
    let plan = locus::bench_farm::Plan {
        scenes,
        width: a.width,
        height: a.height,
        spp: a.spp,
        repeat: a.repeat.max(1),
        workers: a.workers.clone(),
        policies: a.policies.clone(),
        cores,
        large,
        exe: std::env::current_exe().context("finding the locus executable")?,
    };
    let (rows, predictions) = locus::bench_farm::run(&plan)?;
    let md = format!(
        "{}\n{}",
        locus::bench_farm::markdown(&rows),
        locus::bench_farm::prediction_markdown(&predictions)
    );
    print!("{md}");
    if let Some(j) = &a.json {
        let out = serde_json::json!({ "rows": rows, "prediction": predictions });
        std::fs::write(j, serde_json::to_string_pretty(&out)?)
            .with_context(|| format!("writing {}", j.display()))?;
    }
    if let Some(m) = &a.markdown {
        std::fs::write(m, &md).with_context(|| format!("writing {}", m.display()))?;
    }
    locus::bench_farm::check(&rows)
}
