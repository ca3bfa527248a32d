//! Would a control variate at the path vertices pay? (The error-per-second
//! issue's question, stop 81; not a feature.)
//!
//! At a vertex the path tracer estimates the reflected indirect light with
//! one cosine-sampled direction `w`: `scale L(w)`. For any fixed function
//! `g` of direction whose cosine-weighted mean `G(n)` over the hemisphere
//! about the shading normal is known, `scale (L(w) - g(w) + G(n))` has the
//! same mean, and less variance where `g` follows `L`. Here `g` is a
//! second-order spherical harmonic fit of `L` per cell of a GRID^3 grid over
//! the scene (least squares over the vertices of TRAIN_SPP samples a pixel
//! of another seed), so that `G(n)` has a closed form (Ramamoorthi and
//! Hanrahan's convolution with the clamped cosine, checked against Monte
//! Carlo at start). Each path is walked again with the kernel's own calls
//! (`shade`, the BVH's queries) and checked to give the kernel's value to
//! the bit; the term is added at its first VERTICES vertices, weighted by
//! the throughput before each. The probe renders the scene with seeds
//! 1..SEEDS at SPP, with and without the term, and prints the relMSE of
//! each (each pixel's spread over the seeds over the reference's `ref^2 +
//! 1e-2`, averaged over pixels and channels) and their ratio.
//!
//!     cargo run --release -p locus --example cv_probe -- \
//!         scenes/cornell-box/cornell.toml REFERENCE.exr SPP SEEDS GRID TRAIN_SPP VERTICES [independent]
use glam::{DVec3, Vec3};
use locus_core::image_io::Image;
use locus_core::integrator::{DIM_PIXEL, Frame, PathRay, shade};
use locus_core::path::{Kernel, WholeScene};
use locus_core::render::Prepared;
use locus_core::sampler::Sampler;
use locus_core::scene::Scene;
use locus_core::stats::TraceStats;
use rayon::prelude::*;

/// Real spherical harmonics to order 2 (orthonormal).
fn sh9(d: Vec3) -> [f64; 9] {
    let (x, y, z) = (d.x as f64, d.y as f64, d.z as f64);
    [
        0.282_094_8,
        0.488_602_5 * y,
        0.488_602_5 * z,
        0.488_602_5 * x,
        1.092_548_4 * x * y,
        1.092_548_4 * y * z,
        0.315_391_6 * (3.0 * z * z - 1.0),
        1.092_548_4 * x * z,
        0.546_274_2 * (x * x - y * y),
    ]
}

/// The clamped cosine's convolution weights over pi, band by band: the
/// cosine-weighted mean over the hemisphere about `n` of
/// `sum c_k Y_k(w)` is `sum A_k c_k Y_k(n)`.
const A: [f64; 9] = [
    1.0,
    2.0 / 3.0,
    2.0 / 3.0,
    2.0 / 3.0,
    0.25,
    0.25,
    0.25,
    0.25,
    0.25,
];

/// A path vertex that sent a continuation: its cell, shading normal,
/// continuation direction, the throughput before it (the product of the
/// earlier vertices' scales), its own scale, and the radiance its
/// continuation brought back.
#[derive(Clone, Copy)]
struct Vertex {
    cell: usize,
    n: Vec3,
    w: Vec3,
    before: Vec3,
    scale: Vec3,
    l: Vec3,
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        a.len() >= 8,
        "usage: cv_probe SCENE REFERENCE.exr SPP SEEDS GRID TRAIN_SPP VERTICES [independent]"
    );
    let scene = Scene::load(std::path::Path::new(&a[1]))?;
    let reference = Image::read_exr(std::path::Path::new(&a[2]))?;
    let spp: u32 = a[3].parse()?;
    let seeds: u64 = a[4].parse()?;
    let grid: usize = a[5].parse()?;
    let train_spp: u32 = a[6].parse()?;
    let upto: usize = a[7].parse()?;
    let sampler = if a.get(8).map(String::as_str) == Some("independent") {
        Sampler::Independent
    } else {
        Sampler::Sobol
    };
    check_convolution();
    let prep = Prepared::new(scene);
    let (w, h) = (prep.scene.camera.width, prep.scene.camera.height);
    let np = (w * h) as usize;
    let bounds = prep.accel.bounds();
    let ext = bounds.extent();
    let cell_of = |p: Vec3| {
        let c = ((p - bounds.min) / ext * grid as f32)
            .as_uvec3()
            .min(glam::UVec3::splat(grid as u32 - 1));
        (c.z as usize * grid + c.y as usize) * grid + c.x as usize
    };
    let tracer = WholeScene(&prep.accel);
    let base = Kernel {
        sampler,
        ..prep.kernel(prep.scene.settings.max_depth, None)
    };
    // The kernel's value of a camera sample, and the path walked again
    // vertex by vertex with the same calls, its radiance finished from the
    // last vertex back (checked against the kernel's, bit for bit).
    let sample = |seed: u64, x: u32, y: u32, i: u32| -> (Vec3, Vec<Vertex>) {
        let kernel = Kernel { seed, ..base };
        let mut chain = Vec::new();
        let mut st = TraceStats::default();
        let total = kernel.sample(&tracer, x, y, i, &mut chain, &mut st);
        let key = kernel.sample_key(x, y, i);
        let mut q = PathRay::camera(kernel.view.ray(x, y, key.get2d(DIM_PIXEL)), key);
        // Each vertex shaded and whether its shadow segment was clear; for
        // each that sent a continuation (all but the last), its cell,
        // shading normal and the continuation's direction.
        let mut walked = Vec::new();
        let mut info = Vec::new();
        while let Some(hit) = prep.accel.closest(&q.ray, 0.0, f32::INFINITY, &mut st) {
            let s = prep.accel.surface(&hit);
            let mat = &kernel.materials[s.material as usize];
            let sh = shade(
                &q,
                &s.hit,
                &s.verts,
                s.shading,
                mat,
                kernel.lights,
                kernel.max_depth,
                None,
                None,
            );
            let visible = match sh.shadow {
                None => false,
                Some(sr) => !prep.accel.occluded(&sr.ray, 0.0, sr.t_max, &mut st),
            };
            walked.push((sh.vertex, visible));
            let f = Frame::at(q.ray.dir, &s.verts, &s.hit, s.shading);
            match sh.next {
                Some(nq) => {
                    info.push((cell_of(f.p), f.ns, nq.ray.dir));
                    q = nq;
                }
                None => break,
            }
        }
        let mut l = Vec3::ZERO;
        let mut back = vec![Vec3::ZERO; walked.len()];
        for (k, (v, vis)) in walked.iter().enumerate().rev() {
            back[k] = l;
            l = v.finish(*vis, l);
        }
        assert_eq!(l, total, "the walk must be the kernel's path");
        let mut before = Vec3::ONE;
        let mut out = Vec::new();
        for (k, &(cell, n, dir)) in info.iter().enumerate() {
            let scale = walked[k].0.scale;
            out.push(Vertex {
                cell,
                n,
                w: dir,
                before,
                scale,
                l: back[k],
            });
            before *= scale;
        }
        out.truncate(upto);
        (total, out)
    };

    // Training: other seeds, every pixel.
    let records: Vec<Vertex> = (0..np)
        .into_par_iter()
        .flat_map_iter(|p| {
            let (x, y) = (p as u32 % w, p as u32 / w);
            (0..train_spp).flat_map(move |i| sample(7777, x, y, i).1)
        })
        .collect();
    let cells = grid * grid * grid;
    let mut m = vec![[[0.0f64; 9]; 9]; cells];
    let mut b = vec![[DVec3::ZERO; 9]; cells];
    for r in &records {
        let y = sh9(r.w);
        for i in 0..9 {
            for j in 0..9 {
                m[r.cell][i][j] += y[i] * y[j];
            }
            b[r.cell][i] += y[i] * r.l.as_dvec3();
        }
    }
    let coef: Vec<[DVec3; 9]> = (0..cells).map(|c| solve(m[c], b[c])).collect();
    let g = |cell: usize, d: Vec3| -> Vec3 {
        let y = sh9(d);
        (0..9)
            .map(|k| coef[cell][k] * y[k])
            .sum::<DVec3>()
            .as_vec3()
    };
    let gbar = |cell: usize, n: Vec3| -> Vec3 {
        let y = sh9(n);
        (0..9)
            .map(|k| coef[cell][k] * (A[k] * y[k]))
            .sum::<DVec3>()
            .as_vec3()
    };

    // Evaluation: per pixel, per seed, the mean with and without the term.
    let (mut plain, mut cv) = (
        vec![vec![Vec3::ZERO; np]; seeds as usize],
        vec![vec![Vec3::ZERO; np]; seeds as usize],
    );
    for s in 0..seeds {
        let out: Vec<(Vec3, Vec3)> = (0..np)
            .into_par_iter()
            .map(|p| {
                let (x, y) = (p as u32 % w, p as u32 / w);
                let (mut a, mut c) = (Vec3::ZERO, Vec3::ZERO);
                for i in 0..spp {
                    let (total, path) = sample(1 + s, x, y, i);
                    a += total;
                    c += total;
                    for v in path {
                        c += v.before * v.scale * (gbar(v.cell, v.n) - g(v.cell, v.w));
                    }
                }
                (a / spp as f32, c / spp as f32)
            })
            .collect();
        for (p, (a, c)) in out.into_iter().enumerate() {
            plain[s as usize][p] = a;
            cv[s as usize][p] = c;
        }
    }
    let rel = |runs: &Vec<Vec<Vec3>>| -> (f64, f64) {
        let (mut e, mut bias) = (0.0, 0.0);
        for p in 0..np {
            let r = Vec3::from(reference.pixels[p]).as_dvec3();
            let mean = runs.iter().map(|v| v[p].as_dvec3()).sum::<DVec3>() / seeds as f64;
            let var = runs
                .iter()
                .map(|v| (v[p].as_dvec3() - mean).powf(2.0))
                .sum::<DVec3>()
                / (seeds as f64 - 1.0);
            let d = r * r + DVec3::splat(1e-2);
            e += (var / d).element_sum() / 3.0;
            bias += ((mean - r).powf(2.0) / d).element_sum() / 3.0;
        }
        (e / np as f64, bias / np as f64)
    };
    let (ep, bp) = rel(&plain);
    let (ec, bc) = rel(&cv);
    println!(
        "{sampler:?}, {spp} spp, grid {grid}^3, {train_spp} training samples a pixel ({} records), the term at vertices 1..={upto}",
        records.len()
    );
    println!("plain: relMSE {ep:.4e} (the seeds' mean against the reference {bp:.3e})");
    println!("control variate: relMSE {ec:.4e} (the seeds' mean against the reference {bc:.3e})");
    println!("ratio {:.3}", ep / ec);
    Ok(())
}

/// `(M + ridge) c = b` by Gaussian elimination with partial pivoting.
fn solve(mut m: [[f64; 9]; 9], mut b: [DVec3; 9]) -> [DVec3; 9] {
    let tr: f64 = (0..9).map(|i| m[i][i]).sum();
    if tr <= 0.0 {
        return [DVec3::ZERO; 9];
    }
    for (i, row) in m.iter_mut().enumerate() {
        row[i] += 1e-6 * tr;
    }
    for col in 0..9 {
        let piv = (col..9)
            .max_by(|&i, &j| m[i][col].abs().total_cmp(&m[j][col].abs()))
            .unwrap();
        m.swap(col, piv);
        b.swap(col, piv);
        let pivot_row = m[col];
        let bc = b[col];
        for r in col + 1..9 {
            let f = m[r][col] / pivot_row[col];
            for (x, p) in m[r][col..].iter_mut().zip(&pivot_row[col..]) {
                *x -= f * p;
            }
            b[r] -= f * bc;
        }
    }
    let mut x = [DVec3::ZERO; 9];
    for r in (0..9).rev() {
        let mut s = b[r];
        for k in r + 1..9 {
            s -= m[r][k] * x[k];
        }
        x[r] = s / m[r][r];
    }
    x
}

/// The closed form against Monte Carlo: the cosine-weighted mean of a
/// random order-2 function about a few normals.
fn check_convolution() {
    use locus_core::geometry::cosine_hemisphere;
    use locus_core::sampler::SampleKey;
    let c: [f64; 9] = [0.7, -0.3, 0.5, 0.2, 0.4, -0.6, 0.3, 0.1, -0.2];
    for (k, n) in [Vec3::Z, Vec3::X, Vec3::new(0.3, -0.5, 0.8).normalize()]
        .into_iter()
        .enumerate()
    {
        let m = 200_000;
        let mc: f64 = (0..m)
            .map(|i| {
                let u = SampleKey::independent(i, k as u32, 5).get2d(0);
                let y = sh9(cosine_hemisphere(n, u));
                (0..9).map(|j| c[j] * y[j]).sum::<f64>()
            })
            .sum::<f64>()
            / m as f64;
        let y = sh9(n);
        let closed: f64 = (0..9).map(|j| A[j] * c[j] * y[j]).sum();
        assert!(
            (mc - closed).abs() < 5e-3,
            "normal {n}: Monte Carlo {mc}, closed form {closed}"
        );
    }
}
