//! `locus radiosity`: progressive refinement radiosity on this machine,
//! with the image, the meshed solution and the convergence report.

use crate::cli::RadiosityArgs;
use crate::commands::radiosity_farm::{ShotSummary, run_farm, summarize};
use crate::commands::render::progress_bar;
use crate::output::{Written, image_of, sibling, write_image};
use anyhow::{Context, Result};
use locus_core::image_io::Image;
use locus_core::radiosity::output::{render_image, write_mesh_ply, write_ply};
use locus_core::radiosity::shoot::BvhVisibility;
use locus_core::radiosity::{Convergence, Ledger, RadiosityParams, Record, Solver, solve};
use locus_core::render::Prepared;
use locus_core::scene::Scene;
use std::path::Path;
use std::time::Instant;

#[derive(serde::Serialize)]
struct FarmReport {
    workers: u32,
    ring: u32,
    balance: locus_worker::radiosity::Balance,
    packets: u64,
    helped: u64,
    /// Per shot, averaged over all shots.
    shots: ShotSummary,
}

/// The JSON written beside the image.
#[derive(serde::Serialize)]
struct RadiosityReport {
    scene: String,
    image: String,
    mesh: String,
    plot: String,
    params: RadiosityParams,
    threads: usize,
    patches: usize,
    elements: u64,
    vertices: u64,
    mesh_bytes: usize,
    iterations: u64,
    stopped: &'static str,
    load_s: f64,
    bvh_s: f64,
    solve_s: f64,
    image_s: f64,
    visibility_rays: u64,
    rays_per_second: f64,
    unshot_fraction: f64,
    ledger: Ledger,
    convergence: Vec<Record>,
    /// The farm's layout and what it measured, when solved on one.
    farm: Option<FarmReport>,
    error_vs_reference: Option<locus_core::metrics::ErrorMetrics>,
}

pub(crate) fn cmd_radiosity(a: RadiosityArgs) -> Result<()> {
    let p = a.solve.params();
    p.check()?;
    let t = Instant::now();
    let scene = Scene::load(&a.scene)?;
    let load_s = t.elapsed().as_secs_f64();
    let cam = &scene.camera;
    locus_core::limits::check_film(cam.width, cam.height, 2, "this machine")
        .map_err(anyhow::Error::msg)?;
    locus_core::limits::check_settings(a.spp.max(1), 1).map_err(anyhow::Error::msg)?;
    let reference = a.reference.as_deref().map(Image::read_exr).transpose()?;
    if a.solve.ring.is_some() && a.workers == 0 {
        anyhow::bail!("--ring needs --workers: rings are a farm's layout");
    }
    let mut solver =
        Solver::new(&scene, p).with_context(|| format!("meshing {}", a.scene.display()))?;
    let prep = Prepared::new(scene);
    let threads = if a.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        a.threads
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let pb = progress_bar(1000, "radiosity");
    let vis = BvhVisibility(&prep.accel);
    let first = solver.unshot_fraction();
    let mut show = |s: &Solver| {
        if let Some(pb) = &pb {
            // Progress on a log scale from the first unshot fraction to
            // the stopping one.
            let f = s.unshot_fraction().max(p.stop);
            let done = (first / f).ln() / (first / p.stop).ln();
            pb.set_position((done.clamp(0.0, 1.0) * 1000.0) as u64);
        }
    };
    let mut farm = None;
    let conv: Convergence = match a.workers {
        0 => pool.install(|| solve(&mut solver, &vis, &mut show)),
        workers => {
            let ring = a.solve.ring.unwrap_or(workers);
            let balance = a.solve.balance.balance();
            let (conv, measured) =
                run_farm(&mut solver, &prep.scene, workers, ring, balance, &mut show)?;
            farm = Some(FarmReport {
                workers: a.workers,
                ring,
                balance,
                packets: measured.packets,
                helped: measured.helped,
                shots: summarize(&measured, usize::MAX),
            });
            conv
        }
    };
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    let t = Instant::now();
    let (image, _) = pool.install(|| {
        let s = &prep.scene.settings;
        render_image(
            &solver,
            &prep.accel,
            &prep.scene.camera,
            a.spp.max(1),
            s.seed,
            s.sampler,
        )
    });
    let image_s = t.elapsed().as_secs_f64();
    let Written {
        png, json, error, ..
    } = write_image(&image, None, &a.output, a.exposure, reference.as_ref())?;
    let ply = sibling(&a.output, "ply");
    write_ply(&solver, &ply, a.exposure).with_context(|| format!("writing {}", ply.display()))?;
    let svg = a.output.with_extension("convergence.svg");
    plot(&svg, &a.scene, &conv.records)?;
    let report = RadiosityReport {
        scene: a.scene.display().to_string(),
        image: a.output.display().to_string(),
        mesh: ply.display().to_string(),
        plot: svg.display().to_string(),
        params: p,
        threads,
        patches: solver.patches.len(),
        elements: solver.elements,
        vertices: solver.vertices(),
        mesh_bytes: solver.bytes(),
        iterations: solver.iterations,
        stopped: conv.stopped,
        load_s,
        bvh_s: prep.timings.bvh_s,
        solve_s: conv.seconds,
        image_s,
        visibility_rays: solver.stats.rays(),
        rays_per_second: solver.stats.rays() as f64 / conv.seconds.max(1e-9),
        unshot_fraction: solver.unshot_fraction(),
        ledger: solver.ledger(),
        convergence: conv.records,
        farm,
        error_vs_reference: error,
    };
    let text = serde_json::to_string_pretty(&report)?;
    std::fs::write(&json, text).with_context(|| format!("writing {}", json.display()))?;
    println!(
        "wrote {} with {}, {}, {} and {}\n  {} patches, {} elements, {} iterations ({}), unshot {:.2e} of emitted\n  load {:.3}s  bvh {:.3}s  solve {:.3}s  image {:.3}s  {:.2} M visibility rays/s",
        a.output.display(),
        png.display(),
        json.display(),
        ply.display(),
        svg.display(),
        report.patches,
        report.elements,
        report.iterations,
        report.stopped,
        report.unshot_fraction,
        load_s,
        report.bvh_s,
        report.solve_s,
        image_s,
        report.rays_per_second / 1e6
    );
    if let Some(e) = error {
        println!("error vs reference: {e}");
    }
    Ok(())
}

/// Writes a radiosity job's result from the farm: the image (EXR, PNG),
/// the meshed solution (PLY), the convergence plot (SVG) and the report
/// (JSON), as `locus radiosity` does.
pub(crate) fn write_farm_solution(
    scene: &Path,
    output: &Path,
    exposure: f32,
    r: &locus_protocol::submit::JobResult,
    rad: &locus_protocol::radiosity::RadiosityReport,
    reference: Option<&Image>,
) -> Result<()> {
    let Written {
        png, json, error, ..
    } = write_image(&image_of(r), None, output, exposure, reference)?;
    let ply = sibling(output, "ply");
    write_mesh_ply(&rad.mesh, &ply, exposure)
        .with_context(|| format!("writing {}", ply.display()))?;
    let svg = output.with_extension("convergence.svg");
    plot(&svg, scene, &rad.convergence)?;
    #[derive(serde::Serialize)]
    struct Out<'a> {
        scene: String,
        image: String,
        mesh: String,
        plot: String,
        radiosity: &'a locus_protocol::radiosity::RadiosityReport,
        error_vs_reference: Option<locus_core::metrics::ErrorMetrics>,
    }
    let out = Out {
        scene: scene.display().to_string(),
        image: output.display().to_string(),
        mesh: ply.display().to_string(),
        plot: svg.display().to_string(),
        radiosity: rad,
        error_vs_reference: error,
    };
    std::fs::write(&json, serde_json::to_string_pretty(&out)?)
        .with_context(|| format!("writing {}", json.display()))?;
    println!(
        "wrote {} with {}, {}, {} and {}\n  {} nodes in rings of {} ({} balancing): {} patches, {} elements, {} iterations ({}), unshot {:.2e} of emitted\n  mesh {:.3}s  solve {:.3}s  image {:.3}s  {} packets, {} by polling",
        output.display(),
        png.display(),
        json.display(),
        ply.display(),
        svg.display(),
        rad.nodes,
        rad.ring,
        rad.balance.name(),
        rad.patches,
        rad.elements,
        rad.iterations,
        rad.stopped,
        rad.unshot_fraction,
        rad.mesh_s,
        rad.solve_s,
        rad.image_s,
        rad.packets,
        rad.helped,
    );
    Ok(())
}

/// Unshot power and the error against the final solution, against time.
pub(crate) fn plot(path: &Path, scene: &Path, records: &[Record]) -> Result<()> {
    use locus::plot::{Axes, Series, lines};
    let unshot = Series {
        label: "unshot power / emitted".into(),
        points: records
            .iter()
            .map(|r| (r.seconds, r.unshot_fraction))
            .collect(),
        bold: true,
    };
    let error = Series {
        label: "relative L2 error of patch radiosity vs final".into(),
        points: records
            .iter()
            .filter_map(|r| r.error.filter(|&e| e > 0.0).map(|e| (r.seconds, e)))
            .collect(),
        bold: false,
    };
    let axes = Axes {
        x: "solve seconds",
        y: "fraction",
        log_x: false,
        log_y: true,
    };
    let title = format!("radiosity convergence: {}", scene.display());
    lines(path, &title, &axes, &[unshot, error])
}
