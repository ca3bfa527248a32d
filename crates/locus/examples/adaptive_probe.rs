//! Would adaptive sampling pay? The relMSE of a render with the same
//! samples in every pixel against one that spends them where its first
//! `BASE` samples a pixel varied most, at equal total samples and on the
//! same sample keys (the error-per-second issue's question; not a feature):
//! a pixel gets max(BASE, k sqrt(e)) samples, `e` its relative variance
//! (the relMSE weighting of its samples' variance), averaged over the
//! (2 RADIUS + 1)^2 pixels around it, `k` set so the total is SPP a pixel.
//!
//!     cargo run --release -p locus --example adaptive_probe -- \
//!         scenes/cornell-box/cornell.toml REFERENCE.exr 64 16 1 2
//!
//! REFERENCE.exr: a converged render of the scene (`locus render SCENE
//! --spp 4096 --seed 99 -o REFERENCE.exr`).
use glam::Vec3;
use locus_core::image_io::Image;
use locus_core::metrics::compare;
use locus_core::path::WholeScene;
use locus_core::render::Prepared;
use locus_core::scene::Scene;
use locus_core::stats::TraceStats;
use rayon::prelude::*;

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        a.len() == 7,
        "usage: adaptive_probe SCENE REFERENCE.exr SPP BASE RADIUS SEEDS"
    );
    let scene = Scene::load(std::path::Path::new(&a[1]))?;
    let reference = Image::read_exr(std::path::Path::new(&a[2]))?;
    let spp: u32 = a[3].parse()?;
    let base: u32 = a[4].parse()?;
    let radius: i32 = a[5].parse()?;
    let seeds: u64 = a[6].parse()?;
    anyhow::ensure!(
        base >= 2 && base < spp,
        "BASE must be at least 2 and below SPP"
    );
    let prep = Prepared::new(scene);
    let (w, h) = (prep.scene.camera.width, prep.scene.camera.height);
    let np = (w * h) as usize;
    let (mut uni, mut ada) = (0.0, 0.0);
    for seed in 0..seeds {
        let mut kernel = prep.kernel(prep.scene.settings.max_depth, None);
        kernel.seed = 1000 + seed;
        let tracer = WholeScene(&prep.accel);
        let run = |x: u32, y: u32, r: std::ops::Range<u32>| -> (Vec3, Vec3) {
            let mut chain = Vec::new();
            let mut st = TraceStats::default();
            let (mut s, mut q) = (Vec3::ZERO, Vec3::ZERO);
            for i in r {
                let l = kernel.sample(&tracer, x, y, i, &mut chain, &mut st);
                s += l;
                q += l * l;
            }
            (s, q)
        };
        // Uniform.
        let u: Vec<[f32; 3]> = (0..np)
            .into_par_iter()
            .map(|p| {
                let (s, _) = run(p as u32 % w, p as u32 / w, 0..spp);
                (s / spp as f32).to_array()
            })
            .collect();
        let mut img = Image::new(w, h);
        img.pixels = u;
        let eu = compare(&img, &reference)?.rel_mse;
        // Adaptive: phase 1.
        let p1: Vec<(Vec3, Vec3)> = (0..np)
            .into_par_iter()
            .map(|p| run(p as u32 % w, p as u32 / w, 0..base))
            .collect();
        let n0 = base as f32;
        let mean: Vec<Vec3> = p1.iter().map(|(s, _)| *s / n0).collect();
        let var: Vec<Vec3> = p1
            .iter()
            .map(|(s, q)| ((*q - *s * *s / n0) / (n0 - 1.0)).max(Vec3::ZERO))
            .collect();
        let mut e = vec![0.0f64; np];
        for y in 0..h as i32 {
            for x in 0..w as i32 {
                let (mut m, mut v, mut c) = (Vec3::ZERO, Vec3::ZERO, 0.0);
                for dy in -radius..=radius {
                    for dx in -radius..=radius {
                        let (xx, yy) = (x + dx, y + dy);
                        if xx < 0 || yy < 0 || xx >= w as i32 || yy >= h as i32 {
                            continue;
                        }
                        let k = (yy * w as i32 + xx) as usize;
                        m += mean[k];
                        v += var[k];
                        c += 1.0;
                    }
                }
                m /= c;
                v /= c;
                let r = v / (m * m + Vec3::splat(0.01));
                e[(y * w as i32 + x) as usize] = (r.x + r.y + r.z) as f64;
            }
        }
        // n_p = max(n0, lambda sqrt(e_p)), sum = spp * np.
        let total = spp as f64 * np as f64;
        let sq: Vec<f64> = e.iter().map(|v| v.sqrt()).collect();
        let (mut lo, mut hi) = (0.0f64, 1e12f64);
        for _ in 0..100 {
            let l = 0.5 * (lo + hi);
            let s: f64 = sq.iter().map(|s| (l * s).max(n0 as f64)).sum();
            if s > total { hi = l } else { lo = l }
        }
        let n: Vec<u32> = sq
            .iter()
            .map(|s| ((lo * s).max(n0 as f64).round() as u32).min(spp * 16))
            .collect();
        let used: u64 = n.iter().map(|&v| v as u64).sum();
        let a2: Vec<[f32; 3]> = (0..np)
            .into_par_iter()
            .map(|p| {
                let (s2, _) = run(p as u32 % w, p as u32 / w, base..n[p]);
                ((p1[p].0 + s2) / n[p] as f32).to_array()
            })
            .collect();
        img.pixels = a2;
        let ea = compare(&img, &reference)?.rel_mse;
        println!(
            "seed {seed}: uniform {eu:.4e}, adaptive {ea:.4e} (samples {:.3} of uniform), gain {:.3}",
            used as f64 / total,
            eu / ea * total / used as f64
        );
        uni += eu;
        ada += ea;
    }
    println!("mean gain {:.3}", uni / ada);
    Ok(())
}
