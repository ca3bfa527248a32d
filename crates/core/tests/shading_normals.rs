//! Shading normals against a closed form: a diffuse sphere lit by one
//! small square light, direct lighting only (the sphere is convex, so it
//! never lights itself). A point `p` of the exact sphere, with normal `N`,
//! leaves `L = albedo * Le * F(p, N)`, where `F` is the analytic
//! point-to-polygon form factor to the light (Lambert's formula, clipped to
//! the tangent plane; the radiosity solver's own). The sphere is an
//! icosphere written to an OBJ file twice: with its exact vertex normals
//! (`vn`) and without. With them it must shade like the exact sphere, to
//! within the noise of the render; without them every facet is flat and
//! the image is visibly faceted.
//!
//! The tolerance comes from the render's own noise, measured as the spread
//! between two renders with independent seeds; the remaining difference
//! from the closed form is the tessellation's (the camera ray meets a
//! facet a little inside the sphere, and its interpolated normal is not
//! quite the sphere's), bounded here at a tenth of what the flat facets
//! leave. Pixels near the silhouette and near the shadow terminator are
//! left out (see [`exact`]).

mod common;

use glam::Vec3;
use locus_core::radiosity::formfactor::point_to_triangle;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::Scene;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

const ALBEDO: f32 = 0.8;
const LE: f32 = 150.0;

/// The light: a square of side 0.5 at distance 6 towards `dir()`, facing
/// the sphere.
fn light() -> (Vec3, Vec3, Vec3) {
    let l = dir();
    let e1 = l.cross(Vec3::Y).normalize();
    let e2 = l.cross(e1);
    // edge_a x edge_b = -l: the light emits towards the sphere.
    let (a, b) = (e2 * 0.5, e1 * 0.5);
    (l * 6.0 - (a + b) * 0.5, a, b)
}

fn dir() -> Vec3 {
    Vec3::new(1.0, 1.5, 2.0).normalize()
}

/// Writes the sphere (with or without vertex normals) and its scene.
fn write_scene(dir: &Path, normals: bool, seed: u64) -> PathBuf {
    let (v, f) = common::icosphere(3, Vec3::ZERO, 1.0);
    let mut obj = String::new();
    for p in &v {
        writeln!(obj, "v {} {} {}", p.x, p.y, p.z).unwrap();
    }
    if normals {
        for p in &v {
            let n = p.normalize();
            writeln!(obj, "vn {} {} {}", n.x, n.y, n.z).unwrap();
        }
    }
    for t in &f {
        let [a, b, c] = t.map(|i| i + 1);
        if normals {
            writeln!(obj, "f {a}//{a} {b}//{b} {c}//{c}").unwrap();
        } else {
            writeln!(obj, "f {a} {b} {c}").unwrap();
        }
    }
    let name = if normals { "smooth" } else { "flat" };
    std::fs::write(dir.join(format!("{name}.obj")), obj).unwrap();
    let (c, a, b) = light();
    let toml = format!(
        "[camera]\nposition = [0.0, 0.0, 4.0]\nlook_at = [0.0, 0.0, 0.0]\nfov_y = 35.0\n\
         resolution = [48, 48]\n\n[render]\nspp = 64\nmax_depth = 1\nseed = {seed}\n\n\
         [materials.white]\nalbedo = [{ALBEDO}, {ALBEDO}, {ALBEDO}]\n\n\
         [[light]]\ncorner = [{}, {}, {}]\nedge_a = [{}, {}, {}]\nedge_b = [{}, {}, {}]\n\
         emission = [{LE}, {LE}, {LE}]\n\n[[mesh]]\nfile = \"{name}.obj\"\nmaterial = \"white\"\n",
        c.x, c.y, c.z, a.x, a.y, a.z, b.x, b.y, b.z
    );
    let path = dir.join(format!("{name}-{seed}.toml"));
    std::fs::write(&path, toml).unwrap();
    path
}

/// Radiance the exact sphere leaves along the camera ray through film
/// position `(x + u, y + v)`, or None where facets and sphere must
/// disagree whatever the normals: where the ray passes within 3% of the
/// silhouette (or misses), and within 12 degrees of the shadow terminator
/// (the light at more than 78 degrees from the normal), where a facet
/// turns away from the light before the sphere does (the tessellation's
/// shadow terminator, which shading normals do not change).
fn exact(scene: &Scene, x: u32, y: u32, u: [f32; 2]) -> Option<f64> {
    let r = scene.camera.ray(x, y, u);
    // |o + t d|^2 = 1 with |d| = 1.
    let (o, d) = (r.origin.as_dvec3(), r.dir.as_dvec3());
    let b = o.dot(d);
    let disc = b * b - (o.length_squared() - 1.0);
    if disc <= 0.0 || o.length_squared() - b * b > 0.97f64.powi(2) {
        return None;
    }
    let p = o + d * (-b - disc.sqrt());
    let n = p.normalize();
    let (c, a, e) = light();
    let towards = ((c + (a + e) * 0.5).as_dvec3() - p).normalize();
    if n.dot(towards) < 0.2 {
        return None;
    }
    let quad = [[c, c + a, c + a + e], [c, c + a + e, c + e]];
    let f: f64 = quad
        .iter()
        .map(|t| point_to_triangle(p.as_vec3(), n.as_vec3(), t))
        .sum();
    Some(ALBEDO as f64 * LE as f64 * f)
}

/// The closed form over the interior pixels, each averaged over 4 x 4
/// points of the pixel as the renderer's jitter spreads its samples.
fn closed_form(scene: &Scene) -> Vec<Option<f64>> {
    let (w, h) = (scene.camera.width, scene.camera.height);
    let mut out = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            let mut sum = 0.0;
            let mut all = true;
            for k in 0..16 {
                let u = [((k % 4) as f32 + 0.5) / 4.0, ((k / 4) as f32 + 0.5) / 4.0];
                match exact(scene, x, y, u) {
                    Some(l) => sum += l,
                    None => all = false,
                }
            }
            out.push(all.then_some(sum / 16.0));
        }
    }
    out
}

fn luminance(scene_path: &Path) -> (Scene, Vec<f64>) {
    let scene = Scene::load(scene_path).expect("scene loads");
    let prep = Prepared::new(scene.clone());
    let out = render(&prep, &RenderOptions::from_scene(&scene), &|_, _| {});
    let px = out
        .image
        .pixels
        .iter()
        .map(|p| (p[0] as f64 + p[1] as f64 + p[2] as f64) / 3.0)
        .collect();
    (scene, px)
}

/// Mean squared difference relative to the closed form, over the pixels it
/// covers.
fn rel_mse(img: &[f64], truth: &[Option<f64>]) -> f64 {
    let (mut s, mut n) = (0.0, 0);
    for (a, t) in img.iter().zip(truth) {
        if let Some(t) = t {
            s += (a - t).powi(2) / (t * t + 1e-4);
            n += 1;
        }
    }
    s / n as f64
}

#[test]
fn vertex_normals_shade_a_tessellated_sphere_like_the_exact_one() {
    let dir = std::env::temp_dir().join(format!("locus-normals-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (smooth, a) = luminance(&write_scene(&dir, true, 1));
    let (_, b) = luminance(&write_scene(&dir, true, 2));
    let (flat, c) = luminance(&write_scene(&dir, false, 1));
    assert_eq!(
        smooth.load_stats.shaded,
        smooth.tris.len() - 2,
        "all but the light"
    );
    assert!(flat.tri_normals.is_empty());
    let truth = closed_form(&smooth);
    let covered = truth.iter().flatten().count();
    assert!(covered > 500, "{covered} pixels on the lit sphere");
    // Noise: two renders with independent seeds differ by twice the
    // variance of one.
    let noise = {
        let (mut s, mut n) = (0.0, 0);
        for ((x, y), t) in a.iter().zip(&b).zip(&truth) {
            if let Some(t) = t {
                s += (x - y).powi(2) / (t * t + 1e-4);
                n += 1;
            }
        }
        s / n as f64 / 2.0
    };
    let smooth_err = rel_mse(&a, &truth);
    let flat_err = rel_mse(&c, &truth);
    eprintln!(
        "relMSE against the exact sphere: with normals {smooth_err:.3e}, flat {flat_err:.3e}; \
         noise {noise:.3e} over {covered} pixels"
    );
    // What the tessellation leaves once the noise is taken out.
    let (smooth_bias, flat_bias) = (smooth_err - noise, flat_err - noise);
    assert!(
        flat_bias > 20.0 * noise,
        "the flat facets must stand out of the noise: {flat_bias:.3e} against {noise:.3e}"
    );
    assert!(
        smooth_bias < 0.1 * flat_bias,
        "with normals the sphere must shade smooth: {smooth_bias:.3e} against flat {flat_bias:.3e}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
