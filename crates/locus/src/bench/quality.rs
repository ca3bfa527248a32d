//! `locus bench quality`: error per second of the render core, against
//! Mitsuba 3 where it is installed.
//!
//! A converged reference is rendered once (Sobol, its own seeds) and kept
//! in the output folder under its settings. It is rendered as two halves
//! with different seeds, so the reference's own error is measured, not
//! guessed: the relMSE between the halves, over 4, is that of their mean.
//! Then the scene is rendered at each sample count with each of locus's
//! samplers and, when `python3 -c "import mitsuba, numpy"` works, with Mitsuba's
//! `independent` and `ldsampler` on the same threads (the scene exported
//! as PLY files and a JSON spec, rendered by the script beside this file).
//! Every row gets its render time, its relMSE against the reference, their
//! product (lower is better) and the variance a sample leaves (relMSE x
//! spp). Output: quality.md, quality.csv and quality.svg (relMSE against
//! time, log-log).

use anyhow::{Context, Result, bail};
use locus_core::geometry::FLAT;
use locus_core::image_io::Image;
use locus_core::irradiance::IrradianceParams;
use locus_core::metrics::compare;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::sampler::Sampler;
use locus_core::scene::Scene;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The Mitsuba side of the run.
pub struct Mitsuba {
    /// The Python that has `mitsuba` installed.
    pub python: String,
    /// Its variant, e.g. `llvm_ad_rgb`.
    pub variant: String,
    pub samplers: Vec<String>,
}

pub struct Plan {
    pub scene: PathBuf,
    pub out_dir: PathBuf,
    pub spp: Vec<u32>,
    pub reference_spp: u32,
    pub samplers: Vec<Sampler>,
    /// Also render each sampler with adaptive sampling.
    pub adaptive: bool,
    /// Threads for both renderers (0: all cores).
    pub threads: usize,
    pub max_depth: Option<u32>,
    pub mitsuba: Option<Mitsuba>,
    /// Irradiance cache settings to render with too, by preset name.
    pub irradiance: Vec<(String, IrradianceParams)>,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Row {
    /// "locus" or "Mitsuba `<version>` `<variant>`".
    pub renderer: String,
    pub sampler: String,
    pub spp: u32,
    pub seconds: f64,
    pub rel_mse: f64,
    /// The relMSE the render reported from its samples' spread, without
    /// the reference (locus's path-traced rows).
    pub estimated_rel_mse: Option<f64>,
}

impl Row {
    /// Wall time x relMSE: lower is better, flat in spp for an estimator
    /// that converges at 1/N.
    pub fn product(&self) -> f64 {
        self.seconds * self.rel_mse
    }

    /// relMSE x spp: the variance one sample leaves (relative).
    pub fn per_sample(&self) -> f64 {
        self.rel_mse * self.spp as f64
    }
}

/// The outcome: rows, and the reference's own relMSE.
pub struct Outcome {
    pub rows: Vec<Row>,
    pub reference_rel_mse: f64,
    pub title: String,
}

#[derive(Serialize, Deserialize, PartialEq)]
struct ReferenceKey {
    scene: String,
    /// A hash of what is rendered: camera, materials and every triangle,
    /// so an edited mesh file renders the reference again.
    content: u64,
    width: u32,
    height: u32,
    spp: u32,
    max_depth: u32,
    seed: u64,
    reference_rel_mse: f64,
}

/// The converged reference and its own relMSE; reused from `out_dir` when
/// one was rendered with the same settings.
fn reference(plan: &Plan, scene: &Scene, prep: &Prepared) -> Result<(Image, f64)> {
    let mut key = ReferenceKey {
        scene: plan.scene.display().to_string(),
        content: content_hash(scene),
        width: scene.camera.width,
        height: scene.camera.height,
        spp: plan.reference_spp.max(2),
        max_depth: scene.settings.max_depth,
        seed: scene.settings.seed ^ 0x9e11,
        reference_rel_mse: 0.0,
    };
    let exr = plan.out_dir.join("reference.exr");
    let meta = plan.out_dir.join("reference.json");
    if let Ok(text) = std::fs::read_to_string(&meta)
        && let Ok(k) = serde_json::from_str::<ReferenceKey>(&text)
        && k.reference_rel_mse > 0.0
        && (ReferenceKey {
            reference_rel_mse: 0.0,
            ..k
        }) == key
        && let Ok(img) = Image::read_exr(&exr)
    {
        tracing::info!(path = %exr.display(), "reusing the reference");
        return Ok((img, k.reference_rel_mse));
    }
    tracing::info!(spp = key.spp, "rendering the reference in two halves");
    let half = |seed: u64| {
        let mut o = RenderOptions::from_scene(scene);
        o.spp = key.spp / 2;
        o.seed = seed;
        o.sampler = Sampler::Sobol;
        o.threads = plan.threads;
        render(prep, &o, &|_, _| {}).image
    };
    let (a, b) = (half(key.seed), half(key.seed ^ 0xb));
    let mut mean = a.clone();
    for (m, q) in mean.pixels.iter_mut().zip(&b.pixels) {
        for c in 0..3 {
            m[c] = (m[c] + q[c]) * 0.5;
        }
    }
    // a - mean = (a - b) / 2, whose square has the expectation
    // var(half) / 2 = var(mean): the reference's own error.
    key.reference_rel_mse = compare(&a, &mean)?.rel_mse.max(f64::MIN_POSITIVE);
    mean.write_exr(&exr)?;
    std::fs::write(&meta, serde_json::to_string_pretty(&key)?)
        .with_context(|| format!("writing {}", meta.display()))?;
    Ok((mean, key.reference_rel_mse))
}

/// A hash of the camera, the materials and the triangles with theirs.
fn content_hash(scene: &Scene) -> u64 {
    use locus_core::sampler::mix64;
    let c = &scene.camera;
    let camera = [c.position, c.look_at, c.up]
        .into_iter()
        .flat_map(|v| v.to_array())
        .chain([c.fov_y, c.width as f32, c.height as f32]);
    let materials = scene
        .materials
        .iter()
        .flat_map(|m| m.albedo.to_array().into_iter().chain(m.emission.to_array()));
    let tris = scene
        .tris
        .iter()
        .zip(&scene.tri_material)
        .flat_map(|(t, &m)| {
            t.iter()
                .flat_map(|v| v.to_array())
                .chain([f32::from_bits(m)])
        });
    let normals = scene
        .tri_normals
        .iter()
        .flatten()
        .flat_map(|n| n.to_array());
    camera
        .chain(materials)
        .chain(tris)
        .chain(normals)
        .fold(scene.tris.len() as u64, |h, x| {
            mix64(h ^ x.to_bits() as u64)
        })
}

/// Runs the benchmark and writes its tables and plot.
pub fn run(plan: &Plan) -> Result<Outcome> {
    std::fs::create_dir_all(&plan.out_dir)
        .with_context(|| format!("creating {}", plan.out_dir.display()))?;
    let mut scene = Scene::load(&plan.scene)?;
    if let Some(d) = plan.max_depth {
        scene.settings.max_depth = d;
    }
    if scene.tris.is_empty() {
        bail!("{}: scene has no triangles", plan.scene.display());
    }
    let prep = Prepared::new(scene.clone());
    let (reference, reference_rel_mse) = reference(plan, &scene, &prep)?;
    let mut rows = Vec::new();
    let spreads: &[bool] = if plan.adaptive {
        &[false, true]
    } else {
        &[false]
    };
    for (&sampler, &adaptive) in plan
        .samplers
        .iter()
        .flat_map(|s| spreads.iter().map(move |a| (s, a)))
    {
        let name = if adaptive {
            format!("{}, adaptive", sampler.name())
        } else {
            sampler.name().to_string()
        };
        for &spp in &plan.spp {
            let mut o = RenderOptions::from_scene(&scene);
            o.spp = spp;
            o.sampler = sampler;
            o.threads = plan.threads;
            o.adaptive = adaptive;
            let out = render(&prep, &o, &|_, _| {});
            let m = compare(&out.image, &reference)?;
            rows.push(Row {
                renderer: "locus".into(),
                sampler: name.clone(),
                spp,
                seconds: out.render_s,
                rel_mse: m.rel_mse,
                estimated_rel_mse: out.error_estimate.map(|e| e.rel_mse),
            });
            tracing::info!(
                sampler = %name,
                spp,
                seconds = out.render_s,
                rel_mse = m.rel_mse,
                "locus"
            );
        }
    }
    for (name, params) in &plan.irradiance {
        for &spp in &plan.spp {
            let mut o = RenderOptions::from_scene(&scene);
            o.spp = spp;
            o.sampler = Sampler::Sobol;
            o.threads = plan.threads;
            o.irradiance = Some(*params);
            let out = render(&prep, &o, &|_, _| {});
            let m = compare(&out.image, &reference)?;
            let records = out.irradiance.map_or(0, |i| i.records);
            tracing::info!(preset = %name, spp, seconds = out.render_s, rel_mse = m.rel_mse, records, "locus + irradiance");
            rows.push(Row {
                renderer: format!("locus + irradiance cache ({name}: {records} records)"),
                sampler: Sampler::Sobol.name().into(),
                spp,
                seconds: out.render_s,
                rel_mse: m.rel_mse,
                estimated_rel_mse: None,
            });
        }
    }
    // Mitsuba failing (a package missing from its Python, say) loses none
    // of locus's rows: they are written first, then the error is returned.
    let mut mitsuba_failed = None;
    if let Some(mi) = &plan.mitsuba {
        match mitsuba(plan, mi, &scene, &reference) {
            Ok(r) => rows.extend(r),
            Err(e) => mitsuba_failed = Some(e),
        }
    }
    let title = format!(
        "{} {}x{}, max depth {}, {} threads",
        plan.scene.display(),
        scene.camera.width,
        scene.camera.height,
        scene.settings.max_depth,
        if plan.threads == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        } else {
            plan.threads
        }
    );
    let out = Outcome {
        rows,
        reference_rel_mse,
        title,
    };
    write(&plan.out_dir.join("quality.md"), &markdown(&out))?;
    write(&plan.out_dir.join("quality.csv"), &csv(&out.rows))?;
    plot(&plan.out_dir.join("quality.svg"), &out.title, &out.rows)?;
    if let Some(e) = mitsuba_failed {
        return Err(e.context(format!(
            "Mitsuba's rows are missing; locus's are in {}",
            plan.out_dir.join("quality.md").display()
        )));
    }
    Ok(out)
}

fn write(p: &Path, s: &str) -> Result<()> {
    std::fs::write(p, s).with_context(|| format!("writing {}", p.display()))
}

/// Whether `python` can import Mitsuba with `variant`.
pub fn mitsuba_available(python: &str, variant: &str) -> bool {
    std::process::Command::new(python)
        .args([
            "-c",
            // The render script reads Mitsuba's images through numpy,
            // which `pip install mitsuba` does not bring.
            "import sys, numpy, mitsuba as mi; mi.set_variant(sys.argv[1])",
            variant,
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

#[derive(Deserialize)]
struct MitsubaOut {
    version: String,
    runs: Vec<MitsubaRun>,
}

#[derive(Deserialize)]
struct MitsubaRun {
    sampler: String,
    spp: u32,
    seconds: f64,
    image: String,
}

/// Exports the scene, renders it with Mitsuba, and measures its images.
fn mitsuba(plan: &Plan, mi: &Mitsuba, scene: &Scene, reference: &Image) -> Result<Vec<Row>> {
    let dir = plan.out_dir.join("mitsuba");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let spec = export(scene, &dir, plan, mi)?;
    let spec_path = dir.join("spec.json");
    write(&spec_path, &serde_json::to_string_pretty(&spec)?)?;
    let script = dir.join("render.py");
    write(&script, include_str!("quality_mitsuba.py"))?;
    tracing::info!(variant = %mi.variant, "rendering with Mitsuba");
    let result = dir.join("result.json");
    let status = std::process::Command::new(&mi.python)
        .arg(&script)
        .arg(&spec_path)
        .arg(&result)
        .status()
        .with_context(|| format!("running {}", mi.python))?;
    if !status.success() {
        bail!("Mitsuba's render ({}) failed: {status}", script.display());
    }
    let res: MitsubaOut = std::fs::read(&result)
        .map_err(anyhow::Error::from)
        .and_then(|b| Ok(serde_json::from_slice(&b)?))
        .with_context(|| format!("reading {}", result.display()))?;
    let (w, h) = (scene.camera.width, scene.camera.height);
    res.runs
        .iter()
        .map(|r| {
            let path = dir.join(&r.image);
            let bytes =
                std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            if bytes.len() != w as usize * h as usize * 12 {
                bail!(
                    "{}: {} bytes for {w}x{h} RGB f32",
                    path.display(),
                    bytes.len()
                );
            }
            let f: Vec<f32> = bytes
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            let image = Image {
                width: w,
                height: h,
                pixels: f.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect(),
            };
            Ok(Row {
                renderer: format!("Mitsuba {} {}", res.version, mi.variant),
                sampler: r.sampler.clone(),
                spp: r.spp,
                seconds: r.seconds,
                rel_mse: compare(&image, reference)?.rel_mse,
                estimated_rel_mse: None,
            })
        })
        .collect()
}

#[derive(Serialize)]
struct Spec {
    camera: serde_json::Value,
    meshes: Vec<serde_json::Value>,
    max_depth: u32,
    spp: Vec<u32>,
    samplers: Vec<String>,
    threads: usize,
    variant: String,
}

/// The scene for Mitsuba: one binary PLY of unshared triangles per
/// material (with vertex normals when the scene has shading normals; a flat
/// triangle's are its face normal), and the spec the script reads.
fn export(scene: &Scene, dir: &Path, plan: &Plan, mi: &Mitsuba) -> Result<Spec> {
    let mut meshes = Vec::new();
    let shaded = !scene.tri_normals.is_empty();
    for (m, mat) in scene.materials.iter().enumerate() {
        let tris: Vec<usize> = (0..scene.tris.len())
            .filter(|&i| scene.tri_material[i] as usize == m)
            .collect();
        if tris.is_empty() {
            continue;
        }
        let name = format!("mesh{m}.ply");
        let normal_props = if shaded {
            "property float nx\nproperty float ny\nproperty float nz\n"
        } else {
            ""
        };
        let mut b = format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\n\
             property float y\nproperty float z\n{normal_props}element face {}\n\
             property list uchar int vertex_indices\nend_header\n",
            tris.len() * 3,
            tris.len()
        )
        .into_bytes();
        for &i in &tris {
            let t = &scene.tris[i];
            let face = locus_core::geometry::tri_cross(t).normalize();
            let n = scene.tri_normals.get(i).copied().unwrap_or(FLAT);
            for (k, v) in t.iter().enumerate() {
                for c in v.to_array() {
                    b.extend_from_slice(&c.to_le_bytes());
                }
                if shaded {
                    let nv = if n == FLAT { face } else { n[k] };
                    for c in nv.to_array() {
                        b.extend_from_slice(&c.to_le_bytes());
                    }
                }
            }
        }
        for i in 0..tris.len() as i32 {
            b.push(3);
            for k in 0..3i32 {
                b.extend_from_slice(&(3 * i + k).to_le_bytes());
            }
        }
        let path = dir.join(&name);
        std::fs::write(&path, b).with_context(|| format!("writing {}", path.display()))?;
        meshes.push(serde_json::json!({
            "ply": name,
            "albedo": mat.albedo.to_array(),
            "emission": mat.emission.to_array(),
        }));
    }
    let c = &scene.camera;
    Ok(Spec {
        camera: serde_json::json!({
            "position": c.position.to_array(),
            "look_at": c.look_at.to_array(),
            "up": c.up.to_array(),
            "fov_y": c.fov_y,
            "width": c.width,
            "height": c.height,
        }),
        meshes,
        // Mitsuba counts the camera vertex in its depth.
        max_depth: scene.settings.max_depth + 1,
        spp: plan.spp.clone(),
        samplers: mi.samplers.clone(),
        threads: plan.threads,
        variant: mi.variant.clone(),
    })
}

/// The table: one row per renderer, sampler and spp, and, at the end, each
/// Mitsuba row's product over locus's best at the same spp.
pub fn markdown(o: &Outcome) -> String {
    let mut s = format!(
        "# Error per second: {}\n\nThe reference's own relMSE: {:.2e} (from its two halves).\n\n\
         | renderer | sampler | spp | seconds | relMSE | seconds x relMSE | relMSE x spp | relMSE from the samples' spread |\n\
         |---|---|---:|---:|---:|---:|---:|---:|\n",
        o.title, o.reference_rel_mse
    );
    for r in &o.rows {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.3} | {:.3e} | {:.3e} | {:.3e} | {} |",
            r.renderer,
            r.sampler,
            r.spp,
            r.seconds,
            r.rel_mse,
            r.product(),
            r.per_sample(),
            r.estimated_rel_mse
                .map_or(String::new(), |e| format!("{e:.3e}"))
        );
    }
    let best = |spp: u32, locus: bool| {
        o.rows
            .iter()
            // Path tracing against path tracing: the irradiance cache's
            // rows are biased, and compared in their own rows.
            .filter(|r| {
                r.spp == spp
                    && if locus {
                        r.renderer == "locus"
                    } else {
                        r.renderer.starts_with("Mitsuba")
                    }
            })
            .map(Row::product)
            .fold(f64::INFINITY, f64::min)
    };
    let mut spps: Vec<u32> = o.rows.iter().map(|r| r.spp).collect();
    spps.sort_unstable();
    spps.dedup();
    let vs: Vec<String> = spps
        .iter()
        .filter(|&&n| best(n, false).is_finite() && best(n, true).is_finite())
        .map(|&n| format!("{n} spp {:.2}", best(n, true) / best(n, false)))
        .collect();
    if !vs.is_empty() {
        let _ = writeln!(
            s,
            "\nlocus's best seconds x relMSE over Mitsuba's best (below 1: locus leads): {}",
            vs.join(", ")
        );
    }
    s
}

pub fn csv(rows: &[Row]) -> String {
    let mut s =
        String::from("renderer,sampler,spp,seconds,rel_mse,product,per_sample,estimated_rel_mse\n");
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{}",
            r.renderer,
            r.sampler,
            r.spp,
            r.seconds,
            r.rel_mse,
            r.product(),
            r.per_sample(),
            r.estimated_rel_mse.map_or(String::new(), |e| e.to_string())
        );
    }
    s
}

/// relMSE against seconds, log-log, one line per renderer and sampler.
pub fn plot(path: &Path, title: &str, rows: &[Row]) -> Result<()> {
    let series = crate::plot::group(rows.iter().map(|r| {
        (
            format!("{}, {}", r.renderer, r.sampler),
            (r.seconds, r.rel_mse),
            true,
        )
    }));
    let axes = crate::plot::Axes {
        x: "render seconds",
        y: "relMSE against the reference",
        log_x: true,
        log_y: true,
    };
    crate::plot::lines(path, title, &axes, &series)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(renderer: &str, sampler: &str, spp: u32, seconds: f64, rel_mse: f64) -> Row {
        Row {
            renderer: renderer.into(),
            sampler: sampler.into(),
            spp,
            seconds,
            rel_mse,
            estimated_rel_mse: None,
        }
    }

    /// The table compares the best of each side at each spp, and the plot
    /// names every line.
    #[test]
    fn table_ratio_and_plot() {
        let o = Outcome {
            rows: vec![
                row("locus", "sobol", 64, 2.0, 1e-3),
                row("locus", "independent", 64, 2.0, 4e-3),
                row("Mitsuba 3.9 llvm_ad_rgb", "ldsampler", 64, 1.0, 4e-3),
                row("Mitsuba 3.9 llvm_ad_rgb", "independent", 64, 1.0, 8e-3),
                row("locus", "sobol", 256, 8.0, 2e-4),
            ],
            reference_rel_mse: 1e-6,
            title: "t".into(),
        };
        let md = markdown(&o);
        // locus 2e-3 over Mitsuba 4e-3; no Mitsuba row at 256 spp.
        assert!(md.contains("64 spp 0.50"), "{md}");
        assert!(!md.contains("256 spp"), "{md}");
        assert!(md.contains("| locus | sobol | 64 | 2.000 | 1.000e-3 | 2.000e-3 | 6.400e-2 |"));
        assert_eq!(csv(&o.rows).lines().count(), 6);
        let dir = std::env::temp_dir().join(format!("locus-quality-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let svg = dir.join("q.svg");
        plot(&svg, "t", &o.rows).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.contains("<svg") && text.contains("locus, sobol"));
        assert!(text.contains("Mitsuba 3.9 llvm_ad_rgb, ldsampler"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
