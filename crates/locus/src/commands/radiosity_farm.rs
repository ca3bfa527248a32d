//! Radiosity on a farm of nodes in this process (`locus radiosity
//! --workers N`), and the paper's Tables 1-4 (`locus bench radiosity`):
//! the time per shot for N nodes in rings of R under each balancing.

use crate::cli::RadiosityBenchArgs;
use anyhow::{Context, Result, bail};
use locus_core::radiosity::{Convergence, RadiosityParams, Solver, solve_with};
use locus_core::scene::Scene;
use locus_protocol::radiosity::NodeTime;
use locus_worker::radiosity::Balance;
use locus_worker::radiosity::coordinator::FarmTimes;
use locus_worker::radiosity::farm::{self, FarmConfig};
use locus_worker::radiosity::node::Layout;
use std::fmt::Write as _;
use std::time::Duration;

/// How long a shot may go without word from a node.
const STALL: Duration = Duration::from_secs(120);

/// Solves `solver` (meshed from `scene`) on `nodes` nodes in rings of
/// `ring`.
pub(crate) fn run_farm(
    solver: &mut Solver,
    scene: &Scene,
    nodes: u32,
    ring: u32,
    balance: Balance,
    progress: &mut dyn FnMut(&Solver),
) -> Result<(Convergence, FarmTimes)> {
    let rings = locus_scheduler::radiosity::plan(scene, solver, nodes, ring, balance)
        .map_err(anyhow::Error::msg)?;
    let cfg = FarmConfig {
        layout: Layout { nodes, ring },
        dynamic: balance.is_dynamic(),
        seed: scene.settings.seed,
        stall: STALL,
    };
    let (tree, positions, owner) = (&rings.tree, &rings.positions, &rings.owner);
    let mut farm = farm::start(solver, scene, tree, positions, owner, cfg);
    let conv = solve_with(solver, &mut farm, progress);
    if let Some(e) = farm.error {
        bail!("the radiosity farm failed: {e}");
    }
    Ok((conv, farm.measured))
}

/// The first `shots` shots of a run, averaged: what one table cell shows.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub(crate) struct ShotSummary {
    /// Wall seconds per shot.
    pub wall_s: f64,
    /// CPU seconds of the busiest node per shot: the shot's time on
    /// dedicated cores cannot be less.
    pub max_work_s: f64,
    pub mean_work_s: f64,
    /// Of the nodes' time in a shot, the share spent idle or waiting.
    pub idle_share: f64,
    pub helping_s: f64,
}

pub(crate) fn summarize(m: &FarmTimes, shots: usize) -> ShotSummary {
    let k = shots.min(m.times.len()).min(m.shot_s.len());
    if k == 0 {
        return ShotSummary::default();
    }
    let mut s = ShotSummary::default();
    for (shot, wall) in m.times.iter().zip(&m.shot_s).take(k) {
        let n = shot.len().max(1) as f64;
        let work = |t: &NodeTime| t.work_s;
        s.wall_s += wall;
        s.max_work_s += shot.iter().map(work).fold(0.0, f64::max);
        s.mean_work_s += shot.iter().map(work).sum::<f64>() / n;
        let idle: f64 = shot.iter().map(|t| t.idle_s + t.waiting_s).sum();
        let all: f64 = shot.iter().map(|t| t.idle_s + t.waiting_s + t.work_s).sum();
        s.idle_share += if all > 0.0 { idle / all } else { 0.0 };
        s.helping_s += shot.iter().map(|t| t.helping_s).sum::<f64>();
    }
    let k = k as f64;
    s.wall_s /= k;
    s.max_work_s /= k;
    s.mean_work_s /= k;
    s.idle_share /= k;
    s.helping_s /= k;
    s
}

/// `locus bench radiosity`: Tables 1-4 of the paper.
pub(crate) fn cmd_bench_radiosity(a: RadiosityBenchArgs) -> Result<()> {
    let scene = Scene::load(&a.scene)?;
    let params = RadiosityParams {
        patches: a.patches,
        mesh: a.mesh,
        max_iterations: a.shots,
        stop: 1e-9,
        ..RadiosityParams::DEFAULT
    };
    let mut md = format!(
        "# Radiosity load balancing on {}\n\nThe first {} shots, averaged. Each cell: the busiest node's \
         CPU seconds per shot (the shot cannot be faster on dedicated cores), the mean node's, \
         and the share of the nodes' time spent idle or waiting; wall seconds per shot in \
         brackets (all nodes share this machine's cores). Rows: nodes N; columns: ring length R.\n",
        a.scene.display(),
        a.shots
    );
    let mut rows = Vec::new();
    for (t, balance) in Balance::ALL.iter().enumerate() {
        writeln!(
            md,
            "\n## Table {}: {} load balancing\n",
            t + 1,
            balance.name()
        )?;
        let rings: Vec<u32> = a.nodes.clone();
        md += "| N \\ R |";
        for r in &rings {
            write!(md, " {r} |")?;
        }
        md += "\n|---|";
        md += &"---|".repeat(rings.len());
        md += "\n";
        for &n in &a.nodes {
            write!(md, "| {n} |")?;
            for &r in &rings {
                if r > n || !n.is_multiple_of(r) {
                    md += " |";
                    continue;
                }
                let mut solver = Solver::new(&scene, params)
                    .with_context(|| format!("meshing {}", a.scene.display()))?;
                let (_, m) = run_farm(&mut solver, &scene, n, r, *balance, &mut |_| {})?;
                let s = summarize(&m, a.shots as usize);
                write!(
                    md,
                    " {:.3} / {:.3}, {:.0}% ({:.3}) |",
                    s.max_work_s,
                    s.mean_work_s,
                    100.0 * s.idle_share,
                    s.wall_s
                )?;
                eprintln!("{} N={n} R={r}: {s:?}", balance.name());
                rows.push((balance.name(), n, r, s, m.helped));
            }
            md += "\n";
        }
    }
    let out = a
        .out_dir
        .unwrap_or_else(|| std::path::PathBuf::from("bench-out/radiosity"));
    std::fs::create_dir_all(&out)?;
    std::fs::write(out.join("radiosity.md"), &md)?;
    let json = serde_json::to_string_pretty(&rows)?;
    std::fs::write(out.join("radiosity.json"), json)?;
    println!("{md}\nwrote {}", out.join("radiosity.md").display());
    Ok(())
}
