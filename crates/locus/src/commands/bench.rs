//! The benchmark commands: `bench` (tracing throughput), `bench locality`
//! and `bench-farm`; the benchmarks themselves are `locus::bench`.

use crate::cli::*;
use anyhow::{Context, Result, bail};
use locus::bench::{farm, farm_table, locality, partitions, quality, trace};
use locus_core::generate::{RoomParams, write_room};
use locus_core::render::Prepared;
use locus_core::scene::Scene;
use std::path::{Path, PathBuf};

pub(crate) fn default_room() -> Result<PathBuf> {
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

pub(crate) fn cmd_bench_locality(a: LocalityArgs) -> Result<()> {
    if a.scene == Path::new("scenes/generated/room.toml") {
        default_room()?;
    }
    let stem = a
        .scene
        .file_stem()
        .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
    let presets = a.presets;
    let workers = a.workers.max(1);
    let threads = if a.threads_per_worker > 0 {
        a.threads_per_worker
    } else {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        (cores / workers).max(1)
    };
    let plan = locality::Plan {
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
        irradiance: a.irradiance,
    };
    locality::run(&plan)?;
    let md = plan.out_dir.join("locality.md");
    print!(
        "{}",
        std::fs::read_to_string(&md).with_context(|| format!("reading {}", md.display()))?
    );
    println!("\nwrote {}, locality.csv and locality.svg", md.display());
    Ok(())
}

pub(crate) fn cmd_bench_quality(a: QualityArgs) -> Result<()> {
    let stem = a
        .scene
        .file_stem()
        .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
    let mitsuba = if a.no_mitsuba {
        None
    } else if quality::mitsuba_available(&a.python, &a.mitsuba_variant) {
        Some(quality::Mitsuba {
            python: a.python,
            variant: a.mitsuba_variant,
            samplers: a.mitsuba_samplers,
        })
    } else {
        eprintln!(
            "Mitsuba's rows left out: {} cannot import numpy and mitsuba with the {} \
             variant (pip install mitsuba numpy; llvm variants need libLLVM)",
            a.python, a.mitsuba_variant
        );
        None
    };
    let plan = quality::Plan {
        out_dir: a
            .out_dir
            .unwrap_or_else(|| PathBuf::from(format!("bench-out/quality-{stem}"))),
        scene: a.scene,
        spp: a.spp.iter().map(|&n| n.max(1)).collect(),
        reference_spp: a.reference_spp,
        samplers: a.samplers,
        adaptive: a.adaptive_sampling,
        threads: a.threads,
        max_depth: a.max_depth,
        mitsuba,
        irradiance: a
            .irradiance
            .iter()
            .map(|n| Ok((n.clone(), locus::config::Preset::resolve(n)?.irradiance)))
            .collect::<Result<_>>()?,
    };
    let out = quality::run(&plan)?;
    print!("{}", quality::markdown(&out));
    println!(
        "\nwrote {} (quality.md, quality.csv, quality.svg)",
        plan.out_dir.display()
    );
    Ok(())
}

pub(crate) fn cmd_bench(a: BenchArgs) -> Result<()> {
    match a.what {
        Some(BenchWhat::Locality(l)) => return cmd_bench_locality(l),
        Some(BenchWhat::Quality(q)) => return cmd_bench_quality(q),
        Some(BenchWhat::Radiosity(r)) => {
            return crate::commands::radiosity_farm::cmd_bench_radiosity(r);
        }
        None => {}
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
    let rays = trace::rays(&prep, a.rays);
    let mut r = trace::run(&prep, &rays, a.rounds, a.spp, a.threads);
    if let Some(py) = &a.embree_python {
        r.embree = Some(trace::embree(
            &prep,
            &rays,
            a.rounds,
            py,
            Path::new("bench-out/embree"),
        )?);
    }
    println!("scene {} ({} triangles)", path.display(), r.triangles);
    println!("BVH build (obvhs CWBVH): {:.3} s", r.bvh_build_s);
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
    if let Some(e) = &r.embree {
        println!(
            "Embree (embreex), 1 thread: {:.2} Mrays/s (build {:.3} s); locus {:.2} Mrays/s on the same rays, {:.2} of Embree ({} of {} closest hits agree)",
            e.embree_mrays_per_s,
            e.embree_build_s,
            e.locus_mrays_per_s,
            e.ratio,
            e.hits_agree,
            r.rays
        );
    }
    if let Some(j) = a.json {
        std::fs::write(&j, serde_json::to_string_pretty(&r)?)
            .with_context(|| format!("writing {}", j.display()))?;
    }
    Ok(())
}

pub(crate) fn cmd_bench_farm(a: BenchFarmArgs) -> Result<()> {
    // One machine renders in this process, as `locus render` does.
    locus_worker::sys::reuse_freed_memory();
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
        Some(farm::Large {
            path: farm::large_scene(Path::new("scenes/generated"))?,
            workers: 4,
            budget: a.large_budget.0,
        })
    };
    let plan = farm::Plan {
        scenes,
        width: a.width,
        height: a.height,
        spp: a.spp,
        bvh: a.bvh,
        repeat: a.repeat.max(1),
        workers: a.workers.clone(),
        policies: a.policies.clone(),
        random_polling: a.random_polling,
        shared_percent: a.shared_percent.clone(),
        morton: !a.no_morton,
        cores,
        large,
        exe: std::env::current_exe().context("finding the locus executable")?,
        reports: a.reports.clone(),
    };
    if let Some(d) = &a.reports {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    let (rows, predictions) = farm::run(&plan)?;
    let partitions = partitions::compare(&rows);
    let md = format!(
        "{}\n{}\n{}",
        farm_table::markdown(&rows),
        partitions::markdown(&partitions),
        farm_table::prediction_markdown(&predictions)
    );
    print!("{md}");
    if let Some(j) = &a.json {
        let out = serde_json::json!({
            "rows": rows,
            "partitions": partitions,
            "prediction": predictions,
        });
        std::fs::write(j, serde_json::to_string_pretty(&out)?)
            .with_context(|| format!("writing {}", j.display()))?;
    }
    if let Some(m) = &a.markdown {
        std::fs::write(m, &md).with_context(|| format!("writing {}", m.display()))?;
    }
    farm_table::check(&rows)
}
