//! `locus bench-farm`: what the farm costs and gains against one machine
//! on the same cores, measured in one run.
//!
//! For each scene: one machine on all cores; then farms of 1, 2, 4 and 8
//! worker processes (`locus worker` children of this process, threads per
//! worker chosen so that the total is the core count, at least one each)
//! under each fetch policy, Morton's partition beside region growing
//! under `forward`, and with `--random-polling` also `forward` with random
//! polling for hot regions. Every farm image is checked bit for bit against the
//! single machine's. Each row gives:
//! - efficiency: one machine's time over the farm's, for the render phase
//!   and for everything after loading (preparation, distribution, BVH
//!   builds and rendering);
//! - CPU microseconds per forwarded query: the render phase's CPU time of
//!   every worker process (as their kernels counted it) less one machine's
//!   render CPU, over the queries forwarded;
//! - forwards per ray, bytes per sample, load imbalance (render CPU, and
//!   CPU with each worker's setup), and each worker process's peak
//!   resident memory against its budget.
//!
//! Under `forward` it also judges region growing against the Morton
//! baseline over every run ([`super::partitions`]).
//!
//! The large scene (a generated room of about four million triangles) runs
//! on four workers whose budgets are each below the scene's geometry, under
//! `forward` and `adaptive`: a scene that no one of them could hold.

use super::partitions::RunFigures;
use crate::farm::{FarmSpec, LocalFarm};
use anyhow::{Context, Result, bail};
use locus_core::accel::BvhSetting;
use locus_core::generate::{RoomParams, write_room};
use locus_core::image_io::Image;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::Scene;
use locus_protocol::report::{FarmReport, WorkerStats};
use locus_protocol::submit::{FetchPolicy, JobOptions, Partitioner};
use locus_worker::engine::DEDICATED_ENGINE_THREADS;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub struct Plan {
    pub scenes: Vec<PathBuf>,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    /// The BVHs' build quality, one machine's and the farm's alike.
    pub bvh: BvhSetting,
    /// Runs per configuration; the fastest is reported (noise only adds).
    pub repeat: u32,
    pub workers: Vec<usize>,
    pub policies: Vec<FetchPolicy>,
    /// Also `forward` with random polling for hot regions.
    pub random_polling: bool,
    /// Percents of the scene every worker holds beside its region
    /// (`Tuning::shared_percent`): `forward` over region growing is
    /// measured with each, everything else with the first.
    pub shared_percent: Vec<u32>,
    /// `forward` over the Morton baseline's partition beside region
    /// growing's.
    pub morton: bool,
    /// Cores the single machine uses and the farms share.
    pub cores: usize,
    /// The large generated scene and its workers' budget, if wanted.
    pub large: Option<Large>,
    /// The `locus` executable the workers run.
    pub exe: PathBuf,
    /// Where every run's whole report goes, if anywhere.
    pub reports: Option<PathBuf>,
}

pub struct Large {
    pub path: PathBuf,
    pub workers: usize,
    pub budget: u64,
}

#[derive(Clone, Debug, Serialize)]
pub struct Row {
    pub scene: String,
    pub config: String,
    pub workers: usize,
    pub threads_per_worker: usize,
    pub policy: String,
    pub partitioner: String,
    /// `forward`'s share of the scene every worker holds (0 elsewhere).
    pub shared_percent: u32,
    pub random_polling: bool,
    /// Render phase (seconds).
    pub render_s: f64,
    /// After loading: preparation, distribution, builds and rendering.
    pub total_s: f64,
    pub efficiency_render: f64,
    pub efficiency_total: f64,
    /// Render-phase CPU seconds, all processes' workers together.
    pub cpu_s: f64,
    pub us_per_forward: Option<f64>,
    /// The same CPU above one machine's over every ray the farm traced:
    /// what the farm costs a ray however few are forwarded.
    pub us_extra_per_ray: Option<f64>,
    /// One machine's render CPU over the rays it traced (its row only):
    /// what tracing a ray costs on this machine, the yardstick of a
    /// forward's cost.
    pub us_per_ray: Option<f64>,
    /// [`Self::us_per_forward`] over one machine's [`Self::us_per_ray`]:
    /// what a forwarded query costs in rays traced, a figure that moves
    /// far less from one processor to the next than microseconds do.
    pub forward_in_rays: Option<f64>,
    pub forwards_per_ray: f64,
    pub bytes_per_sample: f64,
    /// Ray items (forwarded queries and answers) per message between
    /// workers: each message costs a write, a read and often a wake-up,
    /// whatever it carries.
    pub items_per_message: Option<f64>,
    pub imbalance: f64,
    /// The same with each worker's setup ([`FarmReport::total_imbalance`]).
    pub total_imbalance: f64,
    /// Of the workers' render time, the share they sat idle.
    pub idle_share: f64,
    /// The busiest engine thread's share of its worker's render time
    /// (`WorkerStats::engine_wait_s`): near 1, the serial bookkeeping
    /// holds the tracing pool back. None where there is no such thread
    /// to watch: one machine, and workers of fewer than
    /// [`DEDICATED_ENGINE_THREADS`] threads, whose engine thread traces
    /// too and so reads busy whatever holds it.
    pub engine_busy: Option<f64>,
    /// Random polling: polls sent, and queries handed to pollers.
    pub polls: u64,
    pub handed: u64,
    pub route_nodes: u32,
    /// Peak resident bytes of each worker process, and their budget.
    pub peak_rss: Vec<u64>,
    pub budget: u64,
    pub identical: bool,
    /// Every run's partition figures (the row's other figures are the
    /// fastest run's): see [`super::partitions`].
    pub runs: Vec<RunFigures>,
}

impl Row {
    /// A row of `scene` with nothing measured: one machine's, before its
    /// figures are filled in.
    pub fn blank(scene: &str) -> Self {
        Row {
            scene: scene.to_string(),
            config: String::new(),
            workers: 0,
            threads_per_worker: 0,
            policy: String::new(),
            partitioner: String::new(),
            shared_percent: 0,
            random_polling: false,
            render_s: 0.0,
            total_s: 0.0,
            efficiency_render: 1.0,
            efficiency_total: 1.0,
            cpu_s: 0.0,
            us_per_forward: None,
            us_extra_per_ray: None,
            us_per_ray: None,
            forward_in_rays: None,
            forwards_per_ray: 0.0,
            bytes_per_sample: 0.0,
            items_per_message: None,
            imbalance: 1.0,
            total_imbalance: 1.0,
            idle_share: 0.0,
            engine_busy: None,
            polls: 0,
            handed: 0,
            route_nodes: 0,
            peak_rss: Vec::new(),
            budget: 0,
            identical: true,
            runs: Vec::new(),
        }
    }
}

/// The busiest engine thread's share of its worker's render time, where
/// the workers' engine threads only keep the books (see [`Row::engine_busy`]).
fn engine_busy<'w>(
    threads_per_worker: usize,
    workers: impl Iterator<Item = &'w WorkerStats>,
) -> Option<f64> {
    (threads_per_worker >= DEDICATED_ENGINE_THREADS).then(|| {
        workers
            .map(|s| (s.busy_s - s.engine_wait_s) / (s.busy_s + s.idle_s).max(1e-9))
            .fold(0.0, f64::max)
    })
}

/// The generated four-million-triangle room, written on first use.
pub fn large_scene(dir: &Path) -> Result<PathBuf> {
    let path = dir.join("large.toml");
    if !path.is_file() {
        let p = RoomParams {
            detail: 80,
            resolution: [160, 120],
            spp: 4,
            ..RoomParams::default()
        };
        let (p, n) = write_room(dir, "large", &p)
            .with_context(|| format!("writing the large scene into {}", dir.display()))?;
        tracing::info!(triangles = n, path = %p.display(), "generated the large scene");
    }
    Ok(path)
}

/// How well the two cost models predicted each leaf's work on a scene
/// (Pearson r against a full-depth measurement, on the 4-worker octree).
#[derive(Clone, Debug, Serialize)]
pub struct Prediction {
    pub scene: String,
    pub leaves: usize,
    pub analytic_r: f64,
    pub sampled_r: f64,
    pub sampled_rays: u64,
    pub measured_rays: u64,
    /// BVH steps a ray: the measurement's, counted leaf interval by leaf
    /// interval as the preview counts them, and one machine's render's.
    pub preview_steps_per_ray: f64,
    pub render_steps_per_ray: f64,
}

/// What one machine did: its image's bits and its times.
struct Single {
    bits: Vec<u32>,
    steps_per_ray: f64,
    render_s: f64,
    total_s: f64,
    cpu_s: f64,
    /// Rays traced: camera, shadow and indirect.
    rays: u64,
}

impl Single {
    /// CPU microseconds a ray (None for a render that traced none).
    fn us_per_ray(&self) -> Option<f64> {
        (self.rays > 0).then(|| self.cpu_s / self.rays as f64 * 1e6)
    }
}

fn single(scene: &Scene, cores: usize, repeat: u32) -> Single {
    let mut best: Option<Single> = None;
    for _ in 0..repeat.max(1) {
        let t = Instant::now();
        let mut o = RenderOptions::from_scene(scene);
        // Built as `locus render` builds it for this job.
        let prep = Prepared::for_job(scene.clone(), o.spp);
        o.threads = cores;
        let cpu0 = locus_worker::sys::process_cpu_s();
        let out = render(&prep, &o, &|_, _| {});
        let cpu_s = locus_worker::sys::process_cpu_s() - cpu0;
        let st = &out.stats;
        let rays = st.camera_rays + st.shadow_rays + st.indirect_rays;
        let s = Single {
            bits: out.image.to_bits(),
            steps_per_ray: (st.bvh_nodes + st.tri_tests) as f64 / rays.max(1) as f64,
            render_s: out.render_s,
            total_s: t.elapsed().as_secs_f64(),
            cpu_s,
            rays,
        };
        if best.as_ref().is_none_or(|b| s.render_s < b.render_s) {
            best = Some(s);
        }
    }
    best.expect("at least one run")
}

struct FarmRun {
    spec: FarmSpec,
    policy: FetchPolicy,
    partitioner: Partitioner,
    random_polling: bool,
    shared_percent: u32,
}

/// What `repeat` runs of one configuration gave: the fastest run's
/// report, whether every image matched, and every run's partition figures.
struct Runs {
    best: FarmReport,
    identical: bool,
    figures: Vec<RunFigures>,
}

/// Runs `run` `repeat` times on fresh processes.
fn farm(
    scene: &Scene,
    run: &FarmRun,
    repeat: u32,
    want: &[u32],
    reports: Option<&Path>,
) -> Result<Runs> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let mut best: Option<FarmReport> = None;
    let mut identical = true;
    let mut figures = Vec::new();
    for _ in 0..repeat.max(1) {
        let mut opts = JobOptions {
            workers: run.spec.workers as u32,
            partitioner: run.partitioner,
            fetch: run.policy,
            ..JobOptions::default()
        };
        opts.tuning.random_polling = run.random_polling;
        opts.tuning.shared_percent = run.shared_percent;
        let req = locus_scheduler::client::request(scene, opts);
        let r = rt.block_on(async {
            let farm = LocalFarm::launch(&run.spec).await?;
            let r = farm.render(req, &|_, _| {}).await;
            farm.stop().await?;
            r
        })?;
        let img = Image {
            width: r.width,
            height: r.height,
            pixels: r.pixels,
        };
        identical &= img.to_bits() == want;
        if let Some(d) = reports {
            write_report(d, &r.report, run)?;
        }
        figures.push(RunFigures::of(&r.report));
        if best
            .as_ref()
            .is_none_or(|b| r.report.phases.render_s < b.phases.render_s)
        {
            best = Some(r.report);
        }
    }
    Ok(Runs {
        best: best.expect("at least one run"),
        identical,
        figures,
    })
}

/// Writes `report` into `dir` under a name no other run of the benchmark
/// takes: the scene, the configuration and the first free number.
fn write_report(dir: &Path, report: &FarmReport, run: &FarmRun) -> Result<()> {
    let scene = Path::new(&report.scene).file_stem().map_or_else(
        || report.scene.clone(),
        |s| s.to_string_lossy().into_owned(),
    );
    let stem = format!(
        "{}-{}w-{}-{:?}-{}pc",
        scene,
        run.spec.workers,
        run.policy.name(),
        run.partitioner,
        run.shared_percent
    )
    .replace(|c: char| !c.is_ascii_alphanumeric() && c != '-', "_");
    let path = (0..)
        .map(|i| dir.join(format!("{stem}-{i}.json")))
        .find(|p| !p.exists())
        .expect("a free name");
    std::fs::write(&path, serde_json::to_string_pretty(report)?)
        .with_context(|| format!("writing {}", path.display()))
}

fn row(scene: &str, run: &FarmRun, one: &Single, runs: Runs) -> Row {
    let Runs {
        best: f,
        identical,
        figures,
    } = runs;
    let t = &f.totals;
    let total_s = f.phases.total_s;
    let cpu: f64 = f
        .workers
        .iter()
        .map(|w| w.stats.cpu_s - w.stats.setup_cpu_s)
        .sum();
    let fwd = t.forwarded_out;
    let us_per_forward = (fwd > 0).then(|| (cpu - one.cpu_s) / fwd as f64 * 1e6);
    let messages: u64 = f
        .workers
        .iter()
        .flat_map(|w| &w.stats.peers)
        .map(|p| p.msgs_sent)
        .sum();
    Row {
        scene: scene.to_string(),
        config: format!(
            "{} x {} thr, {}, {:?}{}{}",
            run.spec.workers,
            run.spec.threads_per_worker,
            run.policy.name(),
            run.partitioner,
            if run.policy == FetchPolicy::Forward && run.spec.workers > 1 {
                format!(", {}% shared", run.shared_percent)
            } else {
                String::new()
            },
            if run.random_polling {
                ", random polling"
            } else {
                ""
            }
        ),
        workers: run.spec.workers,
        threads_per_worker: run.spec.threads_per_worker,
        policy: run.policy.name().into(),
        partitioner: format!("{:?}", run.partitioner),
        shared_percent: if run.policy == FetchPolicy::Forward {
            run.shared_percent
        } else {
            0
        },
        random_polling: run.random_polling,
        render_s: f.phases.render_s,
        total_s,
        efficiency_render: one.render_s / f.phases.render_s.max(1e-9),
        efficiency_total: one.total_s / total_s.max(1e-9),
        cpu_s: cpu,
        us_per_forward,
        us_per_ray: None,
        forward_in_rays: us_per_forward.zip(one.us_per_ray()).map(|(f, r)| f / r),
        us_extra_per_ray: {
            let tr = &t.trace;
            let rays = tr.camera_rays + tr.shadow_rays + tr.indirect_rays;
            (rays > 0).then(|| (cpu - one.cpu_s) / rays as f64 * 1e6)
        },
        forwards_per_ray: f.forwarded_fraction,
        bytes_per_sample: f.bytes_per_sample,
        items_per_message: (messages > 0 && fwd > 0)
            .then(|| (fwd + t.answers_out) as f64 / messages as f64),
        imbalance: f.load_imbalance,
        total_imbalance: f.total_imbalance,
        idle_share: t.idle_s / (t.busy_s + t.idle_s).max(1e-9),
        engine_busy: engine_busy(
            run.spec.threads_per_worker,
            f.workers.iter().map(|w| &w.stats),
        ),
        polls: t.polls,
        handed: t.handed_out,
        route_nodes: f.route_leaves,
        peak_rss: f.workers.iter().map(|w| w.stats.peak_rss).collect(),
        budget: run.spec.memory_budget,
        identical,
        runs: figures,
    }
}

/// Runs the plan; returns every row and, per scene but the large one, the
/// cost prediction's quality.
pub fn run(plan: &Plan) -> Result<(Vec<Row>, Vec<Prediction>)> {
    let mut rows = Vec::new();
    let mut predictions = Vec::new();
    let mut scenes: Vec<(PathBuf, Option<&Large>)> =
        plan.scenes.iter().map(|s| (s.clone(), None)).collect();
    if let Some(l) = &plan.large {
        scenes.push((l.path.clone(), Some(l)));
    }
    for (path, large) in scenes {
        let t = Instant::now();
        let mut scene = Scene::load(&path)?;
        let load_s = t.elapsed().as_secs_f64();
        scene.camera.width = plan.width;
        scene.camera.height = plan.height;
        scene.settings.spp = plan.spp;
        scene.settings.bvh = plan.bvh;
        let name = path
            .file_stem()
            .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
        tracing::info!(scene = %name, triangles = scene.tris.len(), load_s, "measuring");
        let one = single(&scene, plan.cores, plan.repeat);
        // What one machine needs for the large scene, measured on a process
        // of its own: the figure the workers' budgets stay below.
        let one_peak = match large {
            Some(_) => vec![single_peak(&plan.exe, &path, plan.cores, plan.bvh)?],
            None => Vec::new(),
        };
        if large.is_none() {
            let prep = Prepared::new(scene.clone());
            let tree = locus_scheduler::job::octree_for(&scene, 4);
            let q = locus_scheduler::cost::quality(&scene, &tree, &prep.accel, &prep.lights);
            predictions.push(Prediction {
                scene: name.clone(),
                leaves: q.leaves,
                analytic_r: q.analytic_r,
                sampled_r: q.sampled_r,
                sampled_rays: q.sampled_rays,
                measured_rays: q.measured_rays,
                preview_steps_per_ray: q.measured_steps_per_ray,
                render_steps_per_ray: one.steps_per_ray,
            });
        }
        rows.push(Row {
            config: format!("one machine, {} threads", plan.cores),
            threads_per_worker: plan.cores,
            render_s: one.render_s,
            total_s: one.total_s,
            cpu_s: one.cpu_s,
            us_per_ray: one.us_per_ray(),
            peak_rss: one_peak,
            ..Row::blank(&name)
        });
        let mut runs = Vec::new();
        let first = plan
            .shared_percent
            .first()
            .copied()
            .unwrap_or(locus_protocol::control::Tuning::default().shared_percent);
        match large {
            Some(l) => {
                for policy in [FetchPolicy::Forward, FetchPolicy::Adaptive] {
                    runs.push(FarmRun {
                        spec: spec(plan, l.workers, l.budget),
                        policy,
                        partitioner: Partitioner::RegionGrowing,
                        random_polling: false,
                        shared_percent: first,
                    });
                }
                if plan.random_polling {
                    runs.push(FarmRun {
                        spec: spec(plan, l.workers, l.budget),
                        policy: FetchPolicy::Forward,
                        partitioner: Partitioner::RegionGrowing,
                        random_polling: true,
                        shared_percent: first,
                    });
                }
            }
            None => {
                for &w in &plan.workers {
                    for &policy in &plan.policies {
                        let each = if policy == FetchPolicy::Forward && w > 1 {
                            &plan.shared_percent[..]
                        } else {
                            &plan.shared_percent[..1]
                        };
                        for &shared_percent in each {
                            runs.push(FarmRun {
                                spec: spec(plan, w, 0),
                                policy,
                                partitioner: Partitioner::RegionGrowing,
                                random_polling: false,
                                shared_percent,
                            });
                        }
                    }
                    if w > 1 && plan.policies.contains(&FetchPolicy::Forward) {
                        if plan.morton {
                            runs.push(FarmRun {
                                spec: spec(plan, w, 0),
                                policy: FetchPolicy::Forward,
                                partitioner: Partitioner::Morton,
                                random_polling: false,
                                shared_percent: first,
                            });
                        }
                        if plan.random_polling {
                            runs.push(FarmRun {
                                spec: spec(plan, w, 0),
                                policy: FetchPolicy::Forward,
                                partitioner: Partitioner::RegionGrowing,
                                random_polling: true,
                                shared_percent: first,
                            });
                        }
                    }
                }
            }
        }
        for r in &runs {
            let runs = farm(&scene, r, plan.repeat, &one.bits, plan.reports.as_deref())?;
            let row = row(&name, r, &one, runs);
            tracing::info!(config = %row.config, render_s = row.render_s, "measured");
            rows.push(row);
        }
    }
    Ok((rows, predictions))
}

/// Peak resident memory in bytes of `locus render` of `scene` on one
/// machine with `cores` threads, as a process of its own (0 where the
/// platform cannot tell).
pub fn single_peak(exe: &Path, scene: &Path, cores: usize, bvh: BvhSetting) -> Result<u64> {
    let out = std::env::temp_dir().join(format!("locus-bench-{}.exr", std::process::id()));
    let mut cmd = std::process::Command::new(exe);
    cmd.arg("render")
        .arg(scene)
        .arg("--threads")
        .arg(cores.to_string())
        .arg("--bvh")
        .arg(bvh.name())
        .arg("-o")
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null());
    let (ok, peak) = locus_worker::sys::run_measuring_peak(&mut cmd)
        .with_context(|| format!("running {}", exe.display()))?;
    for ext in ["exr", "png", "json"] {
        let _ = std::fs::remove_file(out.with_extension(ext));
    }
    if !ok {
        bail!("{} render {} failed", exe.display(), scene.display());
    }
    Ok(peak)
}

fn spec(plan: &Plan, workers: usize, budget: u64) -> FarmSpec {
    FarmSpec {
        workers,
        threads_per_worker: (plan.cores / workers).max(1),
        memory_budget: budget,
        processes: Some(plan.exe.clone()),
        http: None,
        tls: None,
        shared_builds: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats(busy_s: f64, engine_wait_s: f64, idle_s: f64) -> WorkerStats {
        WorkerStats {
            busy_s,
            engine_wait_s,
            idle_s,
            ..WorkerStats::default()
        }
    }

    /// A worker whose engine thread traces too has no bookkeeping share to
    /// report; from `DEDICATED_ENGINE_THREADS` threads up it is the busiest
    /// engine's share of its render time, waits for the pool not counted.
    #[test]
    fn engine_busy_only_where_the_engine_only_keeps_the_books() {
        let w = [stats(9.0, 3.0, 1.0), stats(10.0, 1.0, 0.0)];
        assert_eq!(engine_busy(DEDICATED_ENGINE_THREADS - 1, w.iter()), None);
        let b = engine_busy(DEDICATED_ENGINE_THREADS, w.iter()).unwrap();
        assert!((b - 0.9).abs() < 1e-12, "{b}");
    }
}
