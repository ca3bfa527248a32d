//! `locus bench locality`: paper 000's Tables 1-3 for locus. A converged
//! reference is rendered once on this machine (MIS, no cache, many
//! samples); then every quality preset, with and without the directional
//! cache, under every fetch policy, is rendered on the embedded farm, and
//! each row gets its speed (render time, BVH node visits and triangle
//! tests, gains against the same preset without cache under `forward`:
//! Table 1), its error against the reference (RMSE, relative MSE, SSIM:
//! Table 2), its ray counts (diffuse, local, global, cache lookups, hit
//! ratio: Table 3) and its traffic (messages, bytes, fetched bytes). With
//! `irradiance`, every configuration is also rendered with the preset's
//! irradiance cache (its records' time and bytes counted in the row).
//! Output: a Markdown table, a CSV and an SVG plot of error against time.

use crate::config::Preset;
use crate::farm::FarmSpec;
use anyhow::{Context, Result, bail};
use locus_core::image_io::Image;
use locus_core::metrics::{ErrorMetrics, compare};
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::Scene;
use locus_protocol::report::FarmReport;
use locus_protocol::submit::{FetchPolicy, JobOptions};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub struct Plan {
    pub scene: PathBuf,
    pub width: u32,
    pub height: u32,
    pub workers: usize,
    pub threads_per_worker: usize,
    pub reference_spp: u32,
    /// Built-in preset names or preset files.
    pub presets: Vec<String>,
    pub policies: Vec<FetchPolicy>,
    pub fetch_budget: u64,
    pub out_dir: PathBuf,
    /// Also render every configuration with the preset's irradiance cache.
    pub irradiance: bool,
}

/// One configuration's figures. Gains and ratios are against the row of
/// the same preset without cache under `forward`.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    pub preset: String,
    pub spp: u32,
    pub cache: bool,
    /// Ward's irradiance cache on; `render_s` then includes the time the
    /// scheduler took to make its records.
    pub irradiance: bool,
    pub policy: String,
    pub render_s: f64,
    pub bvh_nodes: u64,
    pub tri_tests: u64,
    pub time_gain: f64,
    pub tests_gain: f64,
    pub rmse: f64,
    pub rel_mse: f64,
    pub ssim: f64,
    /// MSE over the base row's MSE (the paper's 4.78 / 3.37 = 1.42).
    pub mse_ratio: f64,
    /// Base MSE x base time over MSE x time: above 1 means less error at
    /// equal time (error falls as 1 / time for a Monte Carlo renderer).
    pub efficiency_gain: f64,
    pub diffuse: u64,
    pub local: u64,
    pub global: u64,
    pub lookups: u64,
    pub hit_ratio: f64,
    pub messages: u64,
    pub bytes: u64,
    pub forwarded: u64,
    pub fetched_leaves: u64,
    pub fetched_bytes: u64,
    pub cache_bytes: u64,
    /// Traffic over the base row's (messages and bytes between workers).
    pub bytes_ratio: f64,
    /// Irradiance records and their bytes sent to the workers.
    pub records: u64,
    pub records_bytes: u64,
}

#[derive(Serialize, Deserialize, PartialEq)]
struct ReferenceKey {
    scene: String,
    width: u32,
    height: u32,
    spp: u32,
    max_depth: u32,
    seed: u64,
}

/// The converged reference: reused from `out_dir` when one was rendered
/// with the same settings.
fn reference(plan: &Plan, scene: &Scene, max_depth: u32) -> Result<Image> {
    let key = ReferenceKey {
        scene: plan.scene.display().to_string(),
        width: scene.camera.width,
        height: scene.camera.height,
        spp: plan.reference_spp,
        max_depth,
        seed: scene.settings.seed ^ 0x5eed,
    };
    let exr = plan.out_dir.join("reference.exr");
    let meta = plan.out_dir.join("reference.json");
    if let Ok(text) = std::fs::read_to_string(&meta)
        && serde_json::from_str::<ReferenceKey>(&text).is_ok_and(|k| k == key)
        && let Ok(img) = Image::read_exr(&exr)
    {
        tracing::info!(path = %exr.display(), "reusing the reference");
        return Ok(img);
    }
    tracing::info!(spp = key.spp, "rendering the reference");
    let prep = Prepared::new(scene.clone());
    let mut o = RenderOptions::from_scene(scene);
    o.spp = key.spp;
    o.max_depth = max_depth;
    // Independent of every measured render's samples.
    o.seed = key.seed;
    o.threads = 0;
    let out = render(&prep, &o, &|_, _| {});
    out.image.write_exr(&exr)?;
    std::fs::write(&meta, serde_json::to_string_pretty(&key)?)
        .with_context(|| format!("writing {}", meta.display()))?;
    Ok(out.image)
}

fn row_of(
    preset: &Preset,
    (cache, irradiance): (bool, bool),
    policy: FetchPolicy,
    f: &FarmReport,
    e: &ErrorMetrics,
) -> Row {
    let t = &f.totals;
    let c = t.trace.cache;
    let sent = |g: fn(&locus_protocol::report::PeerTraffic) -> u64| -> u64 {
        f.workers.iter().flat_map(|w| &w.stats.peers).map(g).sum()
    };
    Row {
        preset: preset.name.clone(),
        spp: preset.spp,
        cache,
        irradiance,
        policy: policy.name().into(),
        render_s: f.phases.render_s + f.irradiance.map_or(0.0, |i| i.seconds),
        bvh_nodes: t.trace.bvh_nodes,
        tri_tests: t.trace.tri_tests,
        time_gain: 1.0,
        tests_gain: 1.0,
        rmse: e.rmse,
        rel_mse: e.rel_mse,
        ssim: e.ssim,
        mse_ratio: 1.0,
        efficiency_gain: 1.0,
        diffuse: t.trace.indirect_rays,
        local: c.local,
        global: c.global,
        lookups: c.lookups,
        hit_ratio: c.hit_ratio(),
        messages: sent(|p| p.msgs_sent),
        bytes: sent(|p| p.bytes_sent),
        forwarded: t.forwarded_out,
        fetched_leaves: t.fetched_leaves,
        fetched_bytes: t.fetched_bytes,
        cache_bytes: t.cache_memory.bytes,
        bytes_ratio: 1.0,
        records: f.irradiance.map_or(0, |i| i.records),
        records_bytes: f.irradiance.map_or(0, |i| i.bytes_sent + i.bytes_gathered),
    }
}

/// Fills the gains and ratios of every row from its preset's base row.
pub fn relate(rows: &mut [Row]) {
    let bases: Vec<Row> = rows
        .iter()
        .filter(|r| !r.cache && !r.irradiance && r.policy == FetchPolicy::Forward.name())
        .cloned()
        .collect();
    for r in rows.iter_mut() {
        let Some(b) = bases.iter().find(|b| b.preset == r.preset) else {
            continue;
        };
        let (mse, mse_b) = (r.rmse * r.rmse, b.rmse * b.rmse);
        r.time_gain = b.render_s / r.render_s;
        r.tests_gain = (b.bvh_nodes + b.tri_tests) as f64 / (r.bvh_nodes + r.tri_tests) as f64;
        r.mse_ratio = mse / mse_b;
        r.efficiency_gain = (mse_b * b.render_s) / (mse * r.render_s);
        r.bytes_ratio = r.bytes as f64 / b.bytes.max(1) as f64;
    }
}

/// Renders the reference and every configuration; writes the tables and
/// the plot into `plan.out_dir`. Returns the rows.
pub fn run(plan: &Plan) -> Result<Vec<Row>> {
    if plan.presets.is_empty() || plan.policies.is_empty() {
        bail!("at least one preset and one policy are needed");
    }
    std::fs::create_dir_all(&plan.out_dir)
        .with_context(|| format!("creating {}", plan.out_dir.display()))?;
    let presets = plan
        .presets
        .iter()
        .map(|p| Preset::resolve(p))
        .collect::<Result<Vec<_>>>()?;
    let mut scene = Scene::load(&plan.scene)?;
    scene.camera.width = plan.width;
    scene.camera.height = plan.height;
    let max_depth = presets.iter().map(|p| p.max_depth).max().unwrap_or(8);
    let reference = reference(plan, &scene, max_depth)?;
    let mut rows = Vec::new();
    for p in &presets {
        let mut s = scene.clone();
        s.settings.spp = p.spp;
        s.settings.max_depth = p.max_depth;
        let ambient: &[bool] = if plan.irradiance {
            &[false, true]
        } else {
            &[false]
        };
        for (&irradiance, cache) in ambient.iter().flat_map(|i| [(i, false), (i, true)]) {
            for &policy in &plan.policies {
                let opts = JobOptions {
                    workers: plan.workers as u32,
                    cache: cache.then_some(p.cache),
                    irradiance: irradiance.then_some(p.irradiance),
                    fetch: policy,
                    fetch_budget: plan.fetch_budget,
                    ..JobOptions::default()
                };
                let req = locus_scheduler::client::request(&s, opts);
                let spec = FarmSpec::embedded(plan.workers, plan.threads_per_worker);
                let r = crate::farm::render_embedded(req, &spec, &|_, _| {})?;
                let img = Image {
                    width: r.width,
                    height: r.height,
                    pixels: r.pixels,
                };
                let e = compare(&img, &reference)?;
                let row = row_of(p, (cache, irradiance), policy, &r.report, &e);
                tracing::info!(
                    preset = %row.preset,
                    cache,
                    irradiance,
                    policy = %row.policy,
                    seconds = row.render_s,
                    rmse = row.rmse,
                    "measured"
                );
                rows.push(row);
            }
        }
    }
    relate(&mut rows);
    let name = plan
        .scene
        .file_stem()
        .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
    let title = format!(
        "{name}, {}x{}, {} workers x {} thread(s), reference {} spp",
        plan.width, plan.height, plan.workers, plan.threads_per_worker, plan.reference_spp
    );
    write(&plan.out_dir.join("locality.md"), &markdown(&title, &rows))?;
    write(&plan.out_dir.join("locality.csv"), &csv(&rows))?;
    plot(&plan.out_dir.join("locality.svg"), &title, &rows)?;
    Ok(rows)
}

fn write(p: &Path, s: &str) -> Result<()> {
    std::fs::write(p, s).with_context(|| format!("writing {}", p.display()))
}

fn on(b: bool) -> &'static str {
    if b { "on" } else { "off" }
}

/// One Markdown table: the configuration columns, then `cells` per row.
fn table(
    s: &mut String,
    intro: &str,
    header: &[&str],
    rows: &[Row],
    cells: impl Fn(&Row) -> Vec<String>,
) {
    let _ = writeln!(s, "{intro}\n");
    let _ = writeln!(
        s,
        "| preset | cache | irradiance | policy | {} |",
        header.join(" | ")
    );
    let _ = writeln!(s, "|---|---|---|---|{}", "---:|".repeat(header.len()));
    for r in rows {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} |",
            r.preset,
            on(r.cache),
            on(r.irradiance),
            r.policy,
            cells(r).join(" | ")
        );
    }
    s.push('\n');
}

/// The three tables in Markdown.
pub fn markdown(title: &str, rows: &[Row]) -> String {
    let mut s = format!("### {title}\n\n");
    table(
        &mut s,
        "Speed (Table 1): gains against the same preset without cache, forwarding.",
        &[
            "render s",
            "BVH nodes",
            "triangle tests",
            "time gain",
            "tests gain",
        ],
        rows,
        |r| {
            vec![
                format!("{:.3}", r.render_s),
                r.bvh_nodes.to_string(),
                r.tri_tests.to_string(),
                format!("{:.2}", r.time_gain),
                format!("{:.2}", r.tests_gain),
            ]
        },
    );
    table(
        &mut s,
        "Error against the reference (Table 2); efficiency gain > 1 means less error at equal time.",
        &["RMSE", "relMSE", "SSIM", "MSE ratio", "efficiency gain"],
        rows,
        |r| {
            vec![
                format!("{:.5}", r.rmse),
                format!("{:.5}", r.rel_mse),
                format!("{:.4}", r.ssim),
                format!("{:.3}", r.mse_ratio),
                format!("{:.2}", r.efficiency_gain),
            ]
        },
    );
    table(
        &mut s,
        "Rays (Table 3; hit ratio = lookups / (global + lookups)) and traffic between workers.",
        &[
            "diffuse",
            "local",
            "global",
            "lookups",
            "hit ratio",
            "forwarded",
            "messages",
            "MB sent",
            "bytes ratio",
            "fetched leaves",
            "fetched MB",
            "cache MB",
            "records",
            "records MB sent",
        ],
        rows,
        |r| {
            vec![
                r.diffuse.to_string(),
                r.local.to_string(),
                r.global.to_string(),
                r.lookups.to_string(),
                format!("{:.1}%", 100.0 * r.hit_ratio),
                r.forwarded.to_string(),
                r.messages.to_string(),
                format!("{:.2}", r.bytes as f64 / 1e6),
                format!("{:.2}", r.bytes_ratio),
                r.fetched_leaves.to_string(),
                format!("{:.2}", r.fetched_bytes as f64 / 1e6),
                format!("{:.2}", r.cache_bytes as f64 / (1024.0 * 1024.0)),
                r.records.to_string(),
                format!("{:.2}", r.records_bytes as f64 / 1e6),
            ]
        },
    );
    s
}

const CSV_HEADER: &str = "preset,spp,cache,irradiance,policy,render_s,bvh_nodes,tri_tests,time_gain,tests_gain,rmse,rel_mse,ssim,mse_ratio,efficiency_gain,diffuse,local,global,lookups,hit_ratio,messages,bytes,forwarded,fetched_leaves,fetched_bytes,cache_bytes,bytes_ratio,records,records_bytes";

pub fn csv(rows: &[Row]) -> String {
    let mut s = String::from(CSV_HEADER);
    s.push('\n');
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            r.preset,
            r.spp,
            r.cache,
            r.irradiance,
            r.policy,
            r.render_s,
            r.bvh_nodes,
            r.tri_tests,
            r.time_gain,
            r.tests_gain,
            r.rmse,
            r.rel_mse,
            r.ssim,
            r.mse_ratio,
            r.efficiency_gain,
            r.diffuse,
            r.local,
            r.global,
            r.lookups,
            r.hit_ratio,
            r.messages,
            r.bytes,
            r.forwarded,
            r.fetched_leaves,
            r.fetched_bytes,
            r.cache_bytes,
            r.bytes_ratio,
            r.records,
            r.records_bytes
        );
    }
    s
}

/// RMSE against render time, one line per (cache, policy) through the
/// presets; lines with the cache on are drawn bold.
pub fn plot(path: &Path, title: &str, rows: &[Row]) -> Result<()> {
    let series = crate::plot::group(rows.iter().map(|r| {
        let label = if r.irradiance {
            format!("{}, cache {}, irradiance", r.policy, on(r.cache))
        } else {
            format!("{}, cache {}", r.policy, on(r.cache))
        };
        (label, (r.render_s, r.rmse), r.cache)
    }));
    let axes = crate::plot::Axes {
        x: "render seconds",
        y: "RMSE against the reference",
        log_x: false,
        log_y: false,
    };
    crate::plot::lines(path, title, &axes, &series)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(preset: &str, cache: bool, policy: &str, t: f64, rmse: f64, bytes: u64) -> Row {
        Row {
            preset: preset.into(),
            spp: 4,
            cache,
            irradiance: false,
            policy: policy.into(),
            render_s: t,
            bvh_nodes: 100,
            tri_tests: 100,
            time_gain: 0.0,
            tests_gain: 0.0,
            rmse,
            rel_mse: 0.1,
            ssim: 0.9,
            mse_ratio: 0.0,
            efficiency_gain: 0.0,
            diffuse: 10,
            local: 5,
            global: 3,
            lookups: 2,
            hit_ratio: 0.4,
            messages: 7,
            bytes,
            forwarded: 1,
            fetched_leaves: 0,
            fetched_bytes: 0,
            cache_bytes: 0,
            bytes_ratio: 0.0,
            records: 0,
            records_bytes: 0,
        }
    }

    /// Gains are against the same preset's cache-off forwarding row; the
    /// tables have one line per row and the CSV one field per header name.
    #[test]
    fn gains_tables_and_plot() {
        let mut rows = vec![
            row("fast", false, "forward", 2.0, 0.2, 1000),
            row("fast", true, "forward", 1.0, 0.4, 250),
            row("low", false, "forward", 1.0, 0.5, 10),
            // With the irradiance cache: measured against the base, never
            // one itself.
            Row {
                irradiance: true,
                ..row("fast", false, "forward", 4.0, 0.1, 500)
            },
        ];
        relate(&mut rows);
        assert_eq!(rows[3].time_gain, 0.5);
        assert!((rows[3].mse_ratio - 0.25).abs() < 1e-12);
        assert_eq!(rows[0].time_gain, 1.0);
        assert_eq!(rows[1].time_gain, 2.0);
        assert!((rows[1].mse_ratio - 4.0).abs() < 1e-12);
        assert!((rows[1].efficiency_gain - 0.5).abs() < 1e-12);
        assert_eq!(rows[1].bytes_ratio, 0.25);
        assert_eq!(rows[2].time_gain, 1.0);
        let md = markdown("t", &rows);
        assert_eq!(md.lines().filter(|l| l.starts_with("| fast")).count(), 9);
        assert_eq!(md.matches("| fast | off | on | forward |").count(), 3);
        let c = csv(&rows);
        let fields = CSV_HEADER.split(',').count();
        for l in c.lines() {
            assert_eq!(l.split(',').count(), fields, "{l}");
        }
        let dir = std::env::temp_dir().join(format!("locus-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let svg = dir.join("p.svg");
        plot(&svg, "t", &rows).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.contains("<svg") && text.contains("forward, cache on"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
