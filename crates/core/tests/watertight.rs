//! Watertightness: rays from inside a closed, finely tessellated mesh, aimed
//! exactly at its vertices and at points on its shared edges, must never
//! escape. Run at unit scale and far from the origin.

mod common;
use glam::Vec3;
use locus_core::accel::Accel;
use locus_core::geometry::Ray;
use locus_core::sampler::SampleKey;
use locus_core::stats::TraceStats;

fn escapes(center: Vec3, radius: f32, origins: usize) -> (usize, usize) {
    let (v, f) = common::icosphere(5, center, radius);
    let tris: Vec<[Vec3; 3]> = f
        .iter()
        .map(|t| [v[t[0] as usize], v[t[1] as usize], v[t[2] as usize]])
        .collect();
    let ids: Vec<u32> = (0..tris.len() as u32).collect();
    let mag = center.abs().max_element() + radius;
    let accel = Accel::build(&tris, &ids, mag);
    // Targets: every vertex and the midpoint and third points of every edge
    // (the points float rounding puts on either side of the edge).
    let mut targets: Vec<Vec3> = v.clone();
    let mut edges = std::collections::BTreeSet::new();
    for t in &f {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            edges.insert((a.min(b), a.max(b)));
        }
    }
    for (a, b) in edges {
        let (pa, pb) = (v[a as usize], v[b as usize]);
        targets.push((pa + pb) * 0.5);
        targets.push(pa + (pb - pa) / 3.0);
    }
    let mut rays = 0;
    let mut escaped = 0;
    let mut st = TraceStats::default();
    for o in 0..origins {
        let k = SampleKey::independent(o as u64, 0, 99);
        // Origins spread through the inner 80% of the ball, the first at the
        // exact centre.
        let off = if o == 0 {
            Vec3::ZERO
        } else {
            (Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 2.0 - 1.0) * 0.45 * radius
        };
        let origin = center + off;
        for &t in &targets {
            let d = t - origin;
            let ray = Ray::new(origin, d.normalize());
            rays += 1;
            if accel.intersect(&ray, 0.0, f32::INFINITY, &mut st).is_none() {
                escaped += 1;
            }
        }
    }
    (rays, escaped)
}

#[test]
fn no_ray_escapes_a_closed_mesh() {
    let mut total = 0;
    for (center, radius, origins) in [
        (Vec3::ZERO, 1.0, 9),
        (Vec3::new(1.0e4, -2.5e4, 7.0e3), 50.0, 8),
        (Vec3::splat(1e-3), 1e-3, 8),
    ] {
        let (rays, escaped) = escapes(center, radius, origins);
        eprintln!("sphere at {center} r={radius}: {rays} rays, {escaped} escaped");
        assert_eq!(
            escaped, 0,
            "{escaped} of {rays} rays escaped the sphere at {center} r={radius}"
        );
        total += rays;
    }
    assert!(total >= 1_000_000, "only {total} rays");
}
