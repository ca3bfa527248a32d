//! The command line's definitions (clap): the subcommands and their
//! arguments, and how farm options become a job's options.

use anyhow::Result;
use clap::{Parser, Subcommand};
use locus::config::Config;
use locus_protocol::control::Tuning;
use locus_protocol::submit::{CostModel, FetchPolicy, JobOptions, Partitioner};
use locus_protocol::tls::{Tls, TlsFiles};
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "locus",
    version,
    about = "Distributed global-illumination render farm"
)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub(crate) cmd: Cmd,
}

#[derive(Subcommand)]
pub(crate) enum Cmd {
    /// Render a scene to EXR, with a PNG preview and a JSON report beside it.
    Render(RenderArgs),
    /// Solve the scene's diffuse light by progressive refinement radiosity
    /// (Stürzlinger, Schaufler and Volkert) and write the solution seen
    /// from its camera (EXR, PNG, JSON), the meshed solution (PLY) and its
    /// convergence (SVG).
    Radiosity(RadiosityArgs),
    /// Error metrics (RMSE, relative MSE, MAE) between two EXR images.
    Diff {
        image: PathBuf,
        reference: PathBuf,
        /// Fail (exit status 1) unless every pixel is bit for bit the same.
        #[arg(long)]
        exact: bool,
    },
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
    /// Wait for a job submitted earlier (`submit --detach`) and write its
    /// result.
    Attach(AttachArgs),
    /// The farm's state (workers, the running job, the queue), from the
    /// scheduler's status address (`locus scheduler --http`).
    Status {
        /// The scheduler's HTTP host:port, or its URL.
        #[arg(long, env = "LOCUS_HTTP", default_value = "127.0.0.1:8080")]
        http: String,
        /// Print the JSON as served.
        #[arg(long)]
        json: bool,
    },
    /// The farm benchmark: overhead against one machine, speedup, and
    /// region growing against the Morton baseline for 2, 4 and 8 workers.
    BenchFarm(BenchFarmArgs),
    /// Write a farm's TLS certificate and key (self-signed, for the name
    /// "locus"): give both to every node with --tls-cert and --tls-key, or
    /// the certificate alone (--tls-ca) to clients.
    TlsInit {
        /// Directory for cert.pem and key.pem.
        #[arg(short, long, default_value = ".")]
        out_dir: PathBuf,
        /// Replace files that exist.
        #[arg(long)]
        force: bool,
    },
}

#[derive(clap::Args)]
pub(crate) struct BenchFarmArgs {
    /// Scenes to measure; default: the generated room, and the conference
    /// room where ../shared has its mesh.
    pub(crate) scenes: Vec<PathBuf>,
    #[arg(long, default_value_t = 320)]
    pub(crate) width: u32,
    #[arg(long, default_value_t = 240)]
    pub(crate) height: u32,
    #[arg(long, default_value_t = 16)]
    pub(crate) spp: u32,
    /// The BVHs' build quality in every row, one machine's and the
    /// farm's: auto (by samples a triangle), full or quick.
    #[arg(long, default_value = "auto")]
    pub(crate) bvh: locus_core::accel::BvhSetting,
    /// Runs per configuration; the fastest is reported (shared machines
    /// are noisy, and noise only ever adds time), and region growing is
    /// judged against Morton over all of them (means and standard errors
    /// of forwards and imbalance).
    #[arg(long, default_value_t = 1)]
    pub(crate) repeat: u32,
    /// Farm sizes to measure.
    #[arg(long, num_args = 1.., default_values_t = [1usize, 2, 4, 8])]
    pub(crate) workers: Vec<usize>,
    #[arg(long, num_args = 1.., default_values = ["forward", "fetch", "adaptive"])]
    pub(crate) policies: Vec<FetchPolicy>,
    /// Also measure `forward` with random polling for hot regions.
    #[arg(long)]
    pub(crate) random_polling: bool,
    /// Percents of the scene every worker holds beside its region: each
    /// is measured under `forward` with region growing, the first under
    /// everything else.
    #[arg(long, num_args = 1.., default_values_t = [Tuning::default().shared_percent])]
    pub(crate) shared_percent: Vec<u32>,
    /// Leave out the Morton baseline's `forward` rows (to compare two
    /// builds of a change in less time).
    #[arg(long)]
    pub(crate) no_morton: bool,
    /// Cores one machine uses and the farms share (0: all of them).
    #[arg(long, default_value_t = 0)]
    pub(crate) cores: usize,
    /// Each of the 4 workers' memory budget for the large scene.
    #[arg(long, default_value = "160M")]
    pub(crate) large_budget: locus::config::ByteSize,
    /// Leave out the large generated scene (4 million triangles).
    #[arg(long, conflicts_with = "large_only")]
    pub(crate) no_large: bool,
    /// Measure only the large generated scene.
    #[arg(long)]
    pub(crate) large_only: bool,
    /// Write the rows as JSON here too.
    #[arg(long)]
    pub(crate) json: Option<PathBuf>,
    /// Write the Markdown tables here too.
    #[arg(long)]
    pub(crate) markdown: Option<PathBuf>,
    /// Write every farm run's whole report (each worker's counts and CPU
    /// time) into this directory, one JSON file a run: what
    /// `crates/locus/src/bench/fit_costs.py --cpu` fits the partition's
    /// cost model to.
    #[arg(long)]
    pub(crate) reports: Option<PathBuf>,
}

#[derive(clap::Args, Clone)]
pub(crate) struct TokenArgs {
    /// Shared cluster token (or LOCUS_TOKEN, or `token` in --config).
    #[arg(long, env = "LOCUS_TOKEN", hide_env_values = true)]
    pub(crate) token: Option<String>,
    /// A file whose first line is the token (a Compose or Kubernetes
    /// secret), or LOCUS_TOKEN_FILE, or `token_file` in --config.
    #[arg(long, env = "LOCUS_TOKEN_FILE")]
    pub(crate) token_file: Option<PathBuf>,
    /// A TOML config file (see configs/).
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// TLS: this node's certificate (PEM), or LOCUS_TLS_CERT, or `cert`
    /// under `[tls]`. Any TLS setting turns TLS on for every link.
    #[arg(long, env = "LOCUS_TLS_CERT")]
    pub(crate) tls_cert: Option<PathBuf>,
    /// TLS: its private key (PEM), or LOCUS_TLS_KEY, or `key` under `[tls]`.
    #[arg(long, env = "LOCUS_TLS_KEY")]
    pub(crate) tls_key: Option<PathBuf>,
    /// TLS: the farm's certificate authority (PEM), or LOCUS_TLS_CA, or
    /// `ca` under `[tls]`; the node's own certificate when not given.
    #[arg(long, env = "LOCUS_TLS_CA")]
    pub(crate) tls_ca: Option<PathBuf>,
    /// TLS: the name certificates are checked for (default "locus").
    #[arg(long, env = "LOCUS_TLS_SERVER_NAME")]
    pub(crate) tls_server_name: Option<String>,
}

impl TokenArgs {
    /// The config file (empty without --config), the cluster token and the
    /// TLS settings from the flags, the environment or that file. A node
    /// that `accepts` connections needs a certificate and key for TLS.
    pub(crate) fn load(&self, accepts: bool) -> Result<(Config, String, Option<Tls>)> {
        let cfg = Config::load(self.config.as_deref())?;
        let token = cfg.token(
            self.token.clone(),
            self.token_file.as_deref(),
            self.config.as_ref(),
        )?;
        let flags = TlsFiles {
            cert: self.tls_cert.clone(),
            key: self.tls_key.clone(),
            ca: self.tls_ca.clone(),
            server_name: self.tls_server_name.clone(),
        };
        let tls = Tls::load(&cfg.tls.overridden_by(&flags), accepts)?;
        Ok((cfg, token, tls))
    }
}

#[derive(clap::Args)]
pub(crate) struct SchedulerArgs {
    /// host:port to listen on (port 0 picks one and logs it).
    #[arg(long)]
    pub(crate) listen: Option<String>,
    /// host:port for the read-only status page, /status, /metrics and job
    /// previews (or `http` under [scheduler] in --config); none by default.
    #[arg(long)]
    pub(crate) http: Option<String>,
    /// Seconds a worker may be silent (no heartbeat) before it counts as
    /// lost and its job goes on without it (or `worker_timeout_s` under
    /// [scheduler]); 5 by default. Workers send heartbeats five times
    /// within it.
    #[arg(long, value_parser = parse_timeout)]
    pub(crate) worker_timeout: Option<f64>,
    /// Directory where queued and running jobs and their finished tiles are
    /// kept (or `state` under [scheduler]): a scheduler restarted on it
    /// resumes them, and their clients attach again. None by default: a
    /// restart loses the jobs.
    #[arg(long)]
    pub(crate) state: Option<std::path::PathBuf>,
    #[command(flatten)]
    pub(crate) auth: TokenArgs,
}

/// A noise target: a positive relMSE (`limits::check_target`).
pub(crate) fn parse_target(s: &str) -> Result<f64, String> {
    let t: f64 = s
        .parse()
        .map_err(|_| format!("{s:?} is not a number (an estimated relMSE, such as 1e-3)"))?;
    locus_core::limits::check_target(t).map(|()| t)
}

/// A timeout in seconds: positive, finite, at most an hour.
pub(crate) fn parse_timeout(s: &str) -> Result<f64, String> {
    let t: f64 = s
        .parse()
        .map_err(|_| format!("{s:?} is not a number of seconds"))?;
    check_timeout(t)
}

pub(crate) fn check_timeout(t: f64) -> Result<f64, String> {
    if (0.05..=3600.0).contains(&t) {
        Ok(t)
    } else {
        Err(format!("a timeout of {t} s is out of range (0.05 to 3600)"))
    }
}

#[derive(clap::Args)]
pub(crate) struct WorkerArgs {
    /// The scheduler's host:port.
    #[arg(long)]
    pub(crate) scheduler: Option<String>,
    /// host:port for peer links (port 0 picks one; default 0.0.0.0:0, every
    /// interface on a free port, advertised as the address this worker
    /// reaches the scheduler from).
    #[arg(long)]
    pub(crate) listen: Option<String>,
    /// Address peers should dial, if not the bound one.
    #[arg(long)]
    pub(crate) advertise: Option<String>,
    /// Tracing threads (0: all cores).
    #[arg(long)]
    pub(crate) threads: Option<usize>,
    /// Memory this worker's process may use, e.g. 4G (default: no limit):
    /// the scheduler gives it no more of the scene than fits, and it
    /// builds and fetches within it.
    #[arg(long)]
    pub(crate) memory_budget: Option<locus::config::ByteSize>,
    /// The name reports and the status page show (default: the host name).
    #[arg(long, env = "LOCUS_WORKER_NAME")]
    pub(crate) name: Option<String>,
    #[command(flatten)]
    pub(crate) auth: TokenArgs,
}

#[derive(clap::Args, Clone)]
pub(crate) struct FarmArgs {
    /// Partitioner of octree leaves into regions.
    #[arg(long, value_enum, default_value = "region-growing")]
    pub(crate) partitioner: PartitionerArg,
    /// Leaf cost prediction the partitioner balances: analytic, sampled
    /// (the full preview), small (a quarter-size preview), or auto (small
    /// for a job of fewer camera samples than triangles, whose full
    /// preview would cost more than it saves, else sampled).
    #[arg(long, value_enum, default_value = "auto")]
    pub(crate) cost: CostArg,
    /// Most ray items per packet (a packet also leaves when its worker
    /// runs out of work).
    #[arg(long, default_value_t = 1024)]
    pub(crate) packet_size: u32,
    /// Flush deadline of a partly filled packet while its worker is busy,
    /// in microseconds.
    #[arg(long, default_value_t = 1000)]
    pub(crate) flush_us: u32,
    /// Camera samples each worker keeps in flight, scaled by the tiles it
    /// originates; fewer once the scheduler holds less than that for each
    /// worker, so that the workers end together.
    #[arg(long, default_value_t = 65536)]
    pub(crate) max_inflight: u32,
    #[arg(long, default_value_t = 16)]
    pub(crate) tile_size: u32,
    /// What a worker does with a ray reaching another worker's leaf:
    /// forward it, fetch the leaf's geometry, hybrid or adaptive (rent or
    /// buy: the whole scene at the start when that pays and fits, else
    /// leaf by leaf).
    #[arg(long, default_value = "adaptive")]
    pub(crate) fetch: FetchPolicy,
    /// MiB of fetched geometry each worker keeps (LRU-like eviction).
    #[arg(long, default_value_t = 256)]
    pub(crate) fetch_budget_mib: u64,
    /// Random polling for hot regions (the radiosity paper's dynamic load
    /// balancing): an idle worker asks a random peer for queued queries
    /// and traces them, fetching the peer's leaves they cross.
    #[arg(long)]
    pub(crate) random_polling: bool,
    /// Percent of the scene's triangles every worker holds beside its
    /// region when rays are forwarded: the leaves rays cross most per
    /// triangle, into which no ray is then forwarded (0: regions only).
    #[arg(long, default_value_t = Tuning::default().shared_percent)]
    pub(crate) shared_percent: u32,
}

#[derive(clap::ValueEnum, Clone, Copy)]
pub(crate) enum PartitionerArg {
    RegionGrowing,
    Morton,
}

#[derive(clap::ValueEnum, Clone, Copy)]
pub(crate) enum CostArg {
    Analytic,
    Sampled,
    Small,
    Auto,
}

#[derive(clap::Args)]
pub(crate) struct SubmitArgs {
    pub(crate) scene: PathBuf,
    /// The scheduler's host:port.
    #[arg(long)]
    pub(crate) scheduler: Option<String>,
    #[arg(short, long, default_value = "out.exr")]
    pub(crate) output: PathBuf,
    /// Workers to use (0: every registered worker).
    #[arg(long, default_value_t = 0)]
    pub(crate) workers: u32,
    #[arg(long)]
    pub(crate) spp: Option<u32>,
    #[arg(long)]
    pub(crate) max_depth: Option<u32>,
    #[arg(long)]
    pub(crate) seed: Option<u64>,
    /// The sample sequence: sobol (the scene's default) or independent.
    #[arg(long)]
    pub(crate) sampler: Option<locus_core::sampler::Sampler>,
    /// Stop at the end of the first pass whose estimated relMSE is at or
    /// below this (e.g. 1e-3); --spp is then the most a pixel gets.
    #[arg(long, value_parser = parse_target)]
    pub(crate) target_rel_mse: Option<f64>,
    /// The BVHs' build quality: auto (the scene's default: quick for a job
    /// of fewer camera samples than triangles, else full), full or quick.
    /// The image is the same to the bit either way.
    #[arg(long)]
    pub(crate) bvh: Option<locus_core::accel::BvhSetting>,
    /// Adaptive sampling, as `render --adaptive-sampling` (the scene file's
    /// `adaptive_sampling = true` does the same).
    #[arg(long)]
    pub(crate) adaptive_sampling: bool,
    #[arg(long)]
    pub(crate) reference: Option<PathBuf>,
    #[arg(long, default_value_t = 1.0)]
    pub(crate) exposure: f32,
    /// Return once the scheduler has taken the job, printing its id: the
    /// job runs on without this client, and `locus attach` fetches its
    /// image (the scheduler keeps the last 4 results).
    #[arg(long)]
    pub(crate) detach: bool,
    /// What the farm computes: a path-traced render, or a radiosity
    /// solution (the scheduler coordinates, the workers are its nodes).
    #[arg(long, value_enum, default_value_t = JobKindArg::Render)]
    pub(crate) kind: JobKindArg,
    #[command(flatten)]
    pub(crate) radiosity: RadiositySolveArgs,
    #[command(flatten)]
    pub(crate) farm: FarmArgs,
    #[command(flatten)]
    pub(crate) auth: TokenArgs,
}

#[derive(clap::Args)]
pub(crate) struct AttachArgs {
    /// The job's id, as `locus submit --detach` printed it.
    pub(crate) job: u64,
    /// The scheduler's host:port.
    #[arg(long)]
    pub(crate) scheduler: Option<String>,
    #[arg(short, long, default_value = "out.exr")]
    pub(crate) output: PathBuf,
    #[arg(long, default_value_t = 1.0)]
    pub(crate) exposure: f32,
    #[command(flatten)]
    pub(crate) auth: TokenArgs,
}

#[derive(clap::Args)]
pub(crate) struct RenderArgs {
    pub(crate) scene: PathBuf,
    #[arg(short, long, default_value = "out.exr")]
    pub(crate) output: PathBuf,
    #[arg(long)]
    pub(crate) spp: Option<u32>,
    #[arg(long)]
    pub(crate) max_depth: Option<u32>,
    #[arg(long)]
    pub(crate) seed: Option<u64>,
    /// The sample sequence: sobol (the scene's default) or independent.
    #[arg(long)]
    pub(crate) sampler: Option<locus_core::sampler::Sampler>,
    /// Stop at the end of the first pass whose estimated relMSE is at or
    /// below this (e.g. 1e-3); --spp is then the most a pixel gets.
    #[arg(long, value_parser = parse_target)]
    pub(crate) target_rel_mse: Option<f64>,
    /// The BVHs' build quality: auto (the scene's default: quick for a job
    /// of fewer camera samples than triangles, else full), full or quick.
    /// The image is the same to the bit either way.
    #[arg(long)]
    pub(crate) bvh: Option<locus_core::accel::BvhSetting>,
    /// Adaptive sampling: after a pilot of an eighth of --spp (at least 8
    /// samples a pixel), each pass spreads its samples over the pixels by
    /// how much error each still carries, --spp being the mean a pixel
    /// gets (the scene file's `adaptive_sampling = true` does the same).
    /// The image differs from an even render's, and is the same to the bit
    /// on any thread count and on the farm.
    #[arg(long)]
    pub(crate) adaptive_sampling: bool,
    /// Compute threads (0: all cores).
    #[arg(long, default_value_t = 0)]
    pub(crate) threads: usize,
    /// A converged EXR to measure the error against.
    #[arg(long)]
    pub(crate) reference: Option<PathBuf>,
    /// Exposure multiplier for the PNG preview.
    #[arg(long, default_value_t = 1.0)]
    pub(crate) exposure: f32,
    /// Render on the embedded farm with this many workers (scheduler and
    /// workers in this process, linked over loopback TCP); 0 renders on
    /// this machine without the farm.
    #[arg(long, default_value_t = 0)]
    pub(crate) workers: usize,
    /// Tracing threads per embedded worker (0: cores / workers, at least 1).
    #[arg(long, default_value_t = 0)]
    pub(crate) threads_per_worker: usize,
    /// With --workers: serve the farm's status page, /status, /metrics and
    /// the live preview on this address (e.g. 127.0.0.1:8080).
    #[arg(long)]
    pub(crate) http: Option<String>,
    /// A quality preset, built in (accurate, fast, low) or a file like
    /// configs/presets/*.toml: spp, depth and the directional cache's
    /// parameters; --spp and --max-depth override it.
    #[arg(long)]
    pub(crate) preset: Option<String>,
    /// Switch the directional cache on (the preset's parameters, or the
    /// defaults); direct light is then estimated by light sampling alone.
    #[arg(long)]
    pub(crate) cache: bool,
    /// Locality radius in leaf edges (overrides the preset's).
    #[arg(long)]
    pub(crate) cache_radius: Option<f32>,
    /// Switch Ward's irradiance cache on for the first vertex's diffuse
    /// interreflection (the preset's [irradiance] settings, or the
    /// defaults). Biased by design: pass --reference to see its error.
    #[arg(long)]
    pub(crate) irradiance: bool,
    /// Ward's accuracy a (Radiance's -aa), overriding the preset's.
    #[arg(long)]
    pub(crate) irradiance_accuracy: Option<f32>,
    #[command(flatten)]
    pub(crate) farm: FarmArgs,
}

/// The radiosity defaults the flags below show.
const RADIOSITY: locus_core::radiosity::RadiosityParams =
    locus_core::radiosity::RadiosityParams::DEFAULT;

#[derive(clap::Args)]
pub(crate) struct RadiosityArgs {
    pub(crate) scene: PathBuf,
    #[arg(short, long, default_value = "radiosity.exr")]
    pub(crate) output: PathBuf,
    #[command(flatten)]
    pub(crate) solve: RadiositySolveArgs,
    /// Camera rays per pixel of the image (antialiasing only: the solution
    /// itself is noise-free).
    #[arg(long, default_value_t = 16)]
    pub(crate) spp: u32,
    /// Compute threads (0: all cores).
    #[arg(long, default_value_t = 0)]
    pub(crate) threads: usize,
    /// A converged EXR (a path-traced render) to measure the error against.
    #[arg(long)]
    pub(crate) reference: Option<PathBuf>,
    /// Exposure multiplier for the PNG preview and the PLY's colours.
    #[arg(long, default_value_t = 1.0)]
    pub(crate) exposure: f32,
    /// Solve on a farm of this many nodes in this process (0: on this
    /// machine's pool); the solution is the same bits.
    #[arg(long, default_value_t = 0)]
    pub(crate) workers: u32,
}

/// How a radiosity solution is computed and laid out on a farm: shared by
/// `locus radiosity` and `locus submit --kind radiosity`.
#[derive(clap::Args)]
pub(crate) struct RadiositySolveArgs {
    /// Patches (the shooters): edges at most the scene's largest extent
    /// divided by this.
    #[arg(long, default_value_t = RADIOSITY.patches)]
    pub(crate) patches: u32,
    /// Initial mesh: element edges at most the scene's largest extent
    /// divided by this.
    #[arg(long, default_value_t = RADIOSITY.mesh)]
    pub(crate) mesh: u32,
    /// Adaptive subdivision levels below the initial mesh (0: none).
    #[arg(long, default_value_t = RADIOSITY.subdivide)]
    pub(crate) subdivide: u32,
    /// Split an element when its corners differ by more than this fraction
    /// of their mean radiosity.
    #[arg(long, default_value_t = RADIOSITY.threshold)]
    pub(crate) threshold: f32,
    /// Parts of the shooter sampled for visibility, one ray each (M: 1, 4,
    /// 16 or 64).
    #[arg(long, default_value_t = RADIOSITY.shooter_parts)]
    pub(crate) parts: u32,
    /// Stop when the unshot power is below this fraction of the emitted.
    #[arg(long, default_value_t = RADIOSITY.stop)]
    pub(crate) stop: f64,
    #[arg(long, default_value_t = RADIOSITY.max_iterations)]
    pub(crate) max_iterations: u64,
    #[arg(long, default_value_t = RADIOSITY.max_elements)]
    pub(crate) max_elements: u64,
    /// Nodes per ring: each ring holds the scene once, one region per
    /// node (default: one ring of all nodes).
    #[arg(long)]
    pub(crate) ring: Option<u32>,
    /// Load balancing on the farm.
    #[arg(long, value_enum, default_value_t = BalanceArg::Both)]
    pub(crate) balance: BalanceArg,
}

impl RadiositySolveArgs {
    pub(crate) fn params(&self) -> locus_core::radiosity::RadiosityParams {
        locus_core::radiosity::RadiosityParams {
            patches: self.patches,
            mesh: self.mesh,
            subdivide: self.subdivide,
            threshold: self.threshold,
            shooter_parts: self.parts,
            stop: self.stop,
            max_iterations: self.max_iterations,
            max_elements: self.max_elements,
        }
    }
}

/// What `locus submit` asks the farm for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum JobKindArg {
    /// A path-traced image.
    #[default]
    Render,
    /// A progressive refinement radiosity solution, its image from the
    /// scene's camera and its mesh (PLY).
    Radiosity,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub(crate) enum BalanceArg {
    /// Equal numbers of patches per node, regions of equal leaf counts.
    None,
    /// Equal numbers of elements per node, regions of equal predicted cost.
    Static,
    /// Random polling for sample packets of other rings.
    Dynamic,
    Both,
}

impl BalanceArg {
    pub(crate) fn balance(self) -> locus_worker::radiosity::Balance {
        use locus_worker::radiosity::Balance;
        match self {
            BalanceArg::None => Balance::None,
            BalanceArg::Static => Balance::Static,
            BalanceArg::Dynamic => Balance::Dynamic,
            BalanceArg::Both => Balance::Both,
        }
    }
}

#[derive(clap::Args)]
pub(crate) struct RadiosityBenchArgs {
    #[arg(default_value = "scenes/cornell-box/cornell.toml")]
    pub(crate) scene: PathBuf,
    /// Node counts (rows) and ring lengths (columns).
    #[arg(long, num_args = 1.., default_values_t = [1u32, 2, 4, 8])]
    pub(crate) nodes: Vec<u32>,
    /// Shots averaged (the paper: the first four).
    #[arg(long, default_value_t = 4)]
    pub(crate) shots: u64,
    #[arg(long, default_value_t = 4)]
    pub(crate) patches: u32,
    #[arg(long, default_value_t = 32)]
    pub(crate) mesh: u32,
    /// Default bench-out/radiosity.
    #[arg(long)]
    pub(crate) out_dir: Option<PathBuf>,
}

#[derive(Subcommand)]
pub(crate) enum GenWhat {
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
pub(crate) struct BenchArgs {
    #[command(subcommand)]
    pub(crate) what: Option<BenchWhat>,
    /// Scene to measure; default: the generated room (written to
    /// scenes/generated if missing).
    pub(crate) scene: Option<PathBuf>,
    #[arg(long, default_value_t = 500_000)]
    pub(crate) rays: usize,
    #[arg(long, default_value_t = 5)]
    pub(crate) rounds: usize,
    #[arg(long, default_value_t = 4)]
    pub(crate) spp: u32,
    #[arg(long, default_value_t = 0)]
    pub(crate) threads: usize,
    /// Write the results as JSON here too.
    #[arg(long)]
    pub(crate) json: Option<PathBuf>,
    /// A Python with embreex (`pip install embreex`): Embree traces the
    /// same rays, and its throughput is printed beside locus's.
    #[arg(long)]
    pub(crate) embree_python: Option<String>,
}

#[derive(Subcommand)]
pub(crate) enum BenchWhat {
    /// Paper 000's Tables 1-3: every preset with and without the
    /// directional cache, under every fetch policy, on the embedded farm,
    /// against a converged reference; writes locality.md, .csv and .svg.
    Locality(LocalityArgs),
    /// Error per second: a converged reference, then renders at several
    /// sample counts with each sampler, and Mitsuba 3's where it is
    /// installed; writes quality.md, .csv and .svg.
    Quality(QualityArgs),
    /// Paper 003's Tables 1-4: radiosity shots on N nodes in rings of R
    /// with no, static, dynamic and both load balancing, with the busiest
    /// node's work and the idle share; writes radiosity.md and .json.
    Radiosity(RadiosityBenchArgs),
}

#[derive(clap::Args)]
pub(crate) struct QualityArgs {
    #[arg(default_value = "scenes/cornell-box/cornell.toml")]
    pub(crate) scene: PathBuf,
    #[arg(long, num_args = 1.., default_values_t = [16u32, 64, 256, 1024])]
    pub(crate) spp: Vec<u32>,
    /// Samples per pixel of the converged reference (rendered once, in two
    /// halves, and kept in the output folder).
    #[arg(long, default_value_t = 8192)]
    pub(crate) reference_spp: u32,
    #[arg(long, num_args = 1.., default_values = ["sobol", "independent"])]
    pub(crate) samplers: Vec<locus_core::sampler::Sampler>,
    /// Also render each of locus's samplers with adaptive sampling (its
    /// rows say "adaptive" after the sampler).
    #[arg(long)]
    pub(crate) adaptive_sampling: bool,
    /// Threads of both renderers (0: all cores).
    #[arg(long, default_value_t = 0)]
    pub(crate) threads: usize,
    #[arg(long)]
    pub(crate) max_depth: Option<u32>,
    /// The Python with Mitsuba 3 (`pip install mitsuba numpy`); Mitsuba's rows
    /// are left out when it cannot import it.
    #[arg(long, default_value = "python3", env = "LOCUS_MITSUBA_PYTHON")]
    pub(crate) python: String,
    #[arg(long, default_value = "llvm_ad_rgb")]
    pub(crate) mitsuba_variant: String,
    #[arg(long, num_args = 1.., default_values = ["independent", "ldsampler"])]
    pub(crate) mitsuba_samplers: Vec<String>,
    /// Leave Mitsuba out even where it is installed.
    #[arg(long)]
    pub(crate) no_mitsuba: bool,
    /// Also render with Ward's irradiance cache at each of these presets'
    /// [irradiance] settings (Sobol, at every --spp; the overture's time
    /// is part of the render's).
    #[arg(long, num_args = 1..)]
    pub(crate) irradiance: Vec<String>,
    /// Where the tables, the plot and the reference go; default
    /// bench-out/quality-<scene>.
    #[arg(long)]
    pub(crate) out_dir: Option<PathBuf>,
}

#[derive(clap::Args)]
pub(crate) struct LocalityArgs {
    pub(crate) scene: PathBuf,
    #[arg(long, default_value_t = 4)]
    pub(crate) workers: usize,
    /// Tracing threads per worker (0: cores / workers, at least 1).
    #[arg(long, default_value_t = 0)]
    pub(crate) threads_per_worker: usize,
    #[arg(long, default_value_t = 160)]
    pub(crate) width: u32,
    #[arg(long, default_value_t = 120)]
    pub(crate) height: u32,
    /// Samples per pixel of the converged reference (MIS, no cache).
    #[arg(long, default_value_t = 1024)]
    pub(crate) reference_spp: u32,
    /// Presets, built in or files; default: accurate fast low.
    #[arg(long, num_args = 1.., default_values = ["accurate", "fast", "low"])]
    pub(crate) presets: Vec<String>,
    /// Policies to measure.
    #[arg(long, num_args = 1.., default_values = ["forward", "fetch", "hybrid", "adaptive"])]
    pub(crate) policies: Vec<FetchPolicy>,
    #[arg(long, default_value_t = 256)]
    pub(crate) fetch_budget_mib: u64,
    /// Also render every configuration with the preset's irradiance cache.
    #[arg(long)]
    pub(crate) irradiance: bool,
    /// Where the tables, the plot and the reference go; default
    /// bench-out/locality-<scene>.
    #[arg(long)]
    pub(crate) out_dir: Option<PathBuf>,
}

impl FarmArgs {
    pub(crate) fn job_options(&self, workers: u32) -> JobOptions {
        JobOptions {
            workers,
            partitioner: match self.partitioner {
                PartitionerArg::RegionGrowing => Partitioner::RegionGrowing,
                PartitionerArg::Morton => Partitioner::Morton,
            },
            cost_model: match self.cost {
                CostArg::Analytic => CostModel::Analytic,
                CostArg::Sampled => CostModel::Sampled,
                CostArg::Small => CostModel::Small,
                CostArg::Auto => CostModel::Auto,
            },
            tile_size: self.tile_size.max(1),
            tuning: Tuning {
                packet_size: self.packet_size.max(1),
                flush_us: self.flush_us,
                max_inflight: self.max_inflight.max(1),
                random_polling: self.random_polling,
                shared_percent: self.shared_percent,
                ..Tuning::default()
            },
            cache: None,
            irradiance: None,
            fetch: self.fetch,
            fetch_budget: self.fetch_budget_mib << 20,
            detached: false,
        }
    }
}
