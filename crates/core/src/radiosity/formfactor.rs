//! The analytic point-to-polygon form factor (Lambert's formula, as
//! Wallace, Elmquist and Haines use it for ray-traced radiosity) and the
//! shooter's parts whose visibility one sample ray each decides.
//!
//! A differential area at `p` with unit normal `n` sees a polygon with
//! form factor `1/(2 pi) * |sum_i gamma_i n . unit(R_i x R_i+1)|`, where
//! `R_i` runs from `p` to vertex `i` and `gamma_i` is the angle between
//! consecutive `R_i`. It is exact only for the part of the polygon above
//! `p`'s tangent plane, so the polygon is clipped to that half-space
//! first. Everything is computed in f64: a receiver close to a shooter's
//! edge sums nearly cancelling angles.

use glam::{DVec3, Vec3};

/// The polygon `poly` clipped to `{x : n . (x - p) >= 0}` (one
/// Sutherland-Hodgman pass), written into `out`.
fn clip_to_hemisphere(p: DVec3, n: DVec3, poly: &[DVec3], out: &mut Vec<DVec3>) {
    out.clear();
    let d = |x: DVec3| n.dot(x - p);
    for i in 0..poly.len() {
        let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
        let (da, db) = (d(a), d(b));
        if da >= 0.0 {
            out.push(a);
        }
        if (da >= 0.0) != (db >= 0.0) {
            let t = da / (da - db);
            out.push(a + (b - a) * t);
        }
    }
}

/// Form factor from the differential area at `p` (unit normal `n`) to the
/// triangle `tri`, ignoring occlusion. Zero for a triangle wholly below
/// the tangent plane.
pub fn point_to_triangle(p: Vec3, n: Vec3, tri: &[Vec3; 3]) -> f64 {
    let (p, n) = (p.as_dvec3(), n.as_dvec3());
    let poly = tri.map(|v| v.as_dvec3());
    let mut clipped = Vec::with_capacity(4);
    clip_to_hemisphere(p, n, &poly, &mut clipped);
    if clipped.len() < 3 {
        return 0.0;
    }
    let mut sum = 0.0;
    for i in 0..clipped.len() {
        let a = clipped[i] - p;
        let b = clipped[(i + 1) % clipped.len()] - p;
        let c = a.cross(b);
        let len = c.length();
        if len <= 0.0 {
            continue;
        }
        let gamma = len.atan2(a.dot(b));
        sum += gamma * n.dot(c) / len;
    }
    (sum.abs() / (2.0 * std::f64::consts::PI)).min(1.0)
}

/// Triangle `tri` split `levels` times into four (midpoint subdivision):
/// `4^levels` congruent parts of equal area, in a fixed order.
pub fn parts(tri: &[Vec3; 3], levels: u32) -> Vec<[Vec3; 3]> {
    let mut out = vec![*tri];
    for _ in 0..levels {
        out = out.iter().flat_map(split4).collect();
    }
    out
}

/// The four midpoint children of a triangle: three at the corners, then
/// the middle one, each with the parent's winding.
pub fn split4(t: &[Vec3; 3]) -> [[Vec3; 3]; 4] {
    let m01 = (t[0] + t[1]) * 0.5;
    let m12 = (t[1] + t[2]) * 0.5;
    let m20 = (t[2] + t[0]) * 0.5;
    [
        [t[0], m01, m20],
        [m01, t[1], m12],
        [m20, m12, t[2]],
        [m12, m20, m01],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// Disc-free closed form: a differential area facing a coaxial square
    /// of half-side `a` at distance `h` (Howell's catalogue, C-11 with
    /// the square as four right triangles meeting on the axis).
    fn square_on_axis(a: f64, h: f64) -> f64 {
        // For a rectangle a x b with one corner above the point, C-11:
        let corner = |a: f64, b: f64| {
            let (x, y) = (a / h, b / h);
            let sx = (1.0 + x * x).sqrt();
            let sy = (1.0 + y * y).sqrt();
            (x / sx * (y / sx).atan() + y / sy * (x / sy).atan()) / (2.0 * PI)
        };
        4.0 * corner(a, a)
    }

    fn square(a: f32, h: f32) -> [[Vec3; 3]; 2] {
        let v = |x, y| Vec3::new(x, y, h);
        [
            [v(-a, -a), v(a, -a), v(a, a)],
            [v(-a, -a), v(a, a), v(-a, a)],
        ]
    }

    #[test]
    fn a_coaxial_square_matches_its_closed_form() {
        for (a, h) in [(1.0f32, 1.0f32), (0.5, 3.0), (4.0, 0.25)] {
            let f: f64 = square(a, h)
                .iter()
                .map(|t| point_to_triangle(Vec3::ZERO, Vec3::Z, t))
                .sum();
            let want = square_on_axis(a as f64, h as f64);
            assert!(
                (f - want).abs() < 1e-6 * want.max(1e-3),
                "{a} {h}: {f} vs {want}"
            );
        }
    }

    #[test]
    fn a_plane_covering_the_hemisphere_has_form_factor_one() {
        // A huge square just above the point covers nearly all of it.
        let f: f64 = square(1e4, 1.0)
            .iter()
            .map(|t| point_to_triangle(Vec3::ZERO, Vec3::Z, t))
            .sum();
        assert!((f - 1.0).abs() < 1e-3, "{f}");
    }

    #[test]
    fn clipping_keeps_only_what_lies_above_the_tangent_plane() {
        // A square standing on the plane through the point, centred on it:
        // only its upper half counts, and that equals the form factor of
        // the half alone.
        let wall = |z0: f32| {
            let v = |x: f32, z: f32| Vec3::new(x, 1.0, z);
            [
                [v(-1.0, z0), v(1.0, z0), v(1.0, 1.0)],
                [v(-1.0, z0), v(1.0, 1.0), v(-1.0, 1.0)],
            ]
        };
        let ff = |w: [[Vec3; 3]; 2]| -> f64 {
            w.iter()
                .map(|t| point_to_triangle(Vec3::ZERO, Vec3::Z, t))
                .sum()
        };
        let (whole, half) = (ff(wall(-1.0)), ff(wall(0.0)));
        assert!(half > 0.01);
        assert!((whole - half).abs() < 1e-9, "{whole} vs {half}");
        // Wholly below: nothing.
        let below = [[
            Vec3::new(0.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, -1.0),
            Vec3::new(0.0, 1.0, -1.0),
        ]];
        assert_eq!(ff2(&below), 0.0);
        fn ff2(t: &[[Vec3; 3]]) -> f64 {
            point_to_triangle(Vec3::ZERO, Vec3::Z, &t[0])
        }
    }

    #[test]
    fn parts_add_up_to_the_whole() {
        let t = [
            Vec3::new(-1.0, -0.5, 2.0),
            Vec3::new(2.0, 0.0, 1.0),
            Vec3::new(0.0, 1.5, 1.5),
        ];
        let whole = point_to_triangle(Vec3::ZERO, Vec3::Z, &t);
        for levels in 0..4 {
            let ps = parts(&t, levels);
            assert_eq!(ps.len(), 1 << (2 * levels));
            let sum: f64 = ps
                .iter()
                .map(|q| point_to_triangle(Vec3::ZERO, Vec3::Z, q))
                .sum();
            assert!(
                (sum - whole).abs() < 1e-6 * whole,
                "{levels}: {sum} vs {whole}"
            );
        }
    }

    #[test]
    fn a_small_distant_patch_approaches_the_differential_form_factor() {
        // cos cos A / (pi r^2) for a small facing square on the axis.
        let (a, h) = (0.01f32, 2.0f32);
        let f: f64 = square(a, h)
            .iter()
            .map(|t| point_to_triangle(Vec3::ZERO, Vec3::Z, t))
            .sum();
        let area = (2.0 * a as f64).powi(2);
        let want = area / (PI * (h as f64).powi(2));
        assert!((f - want).abs() < 1e-4 * want, "{f} vs {want}");
    }
}
