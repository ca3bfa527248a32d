//! Generated test scenes: a conference-like room (walls, a long table, many
//! chairs, ceiling light panels) with a triangle count chosen by the caller,
//! written as OBJ + MTL + scene TOML so it goes through the same loaders as
//! any user scene; the furnace and mesh builders of the core's tests; and
//! the incoherent rays the tracing benchmarks shoot. Output is a pure
//! function of the parameters. It lives in the core, not with the
//! benchmarks, because the core's own tests use it.

use crate::geometry::Ray;
use crate::render::Prepared;
use crate::sampler::SampleKey;
use glam::Vec3;
use std::fmt::Write as _;
use std::path::Path;

#[derive(Clone, Copy, Debug)]
pub struct RoomParams {
    /// Chairs along each long side of the table.
    pub chairs_per_side: u32,
    /// Subdivisions per box face edge (chair parts, table).
    pub detail: u32,
    /// Segments around each chair leg.
    pub leg_segments: u32,
    pub resolution: [u32; 2],
    pub spp: u32,
}

impl Default for RoomParams {
    /// About 330,000 triangles.
    fn default() -> Self {
        Self {
            chairs_per_side: 12,
            detail: 21,
            leg_segments: 24,
            resolution: [320, 240],
            spp: 16,
        }
    }
}

/// Indexed mesh builder that keeps per-face materials.
#[derive(Default)]
pub struct MeshBuilder {
    pub positions: Vec<Vec3>,
    /// (v0, v1, v2, material index)
    pub faces: Vec<[u32; 4]>,
}

impl MeshBuilder {
    /// The faces as (vertices, material) pairs, the input of
    /// [`crate::scene::Scene::from_triangles`].
    pub fn tagged_triangles(&self) -> Vec<([Vec3; 3], u32)> {
        let p = |i: u32| self.positions[i as usize];
        self.faces
            .iter()
            .map(|f| ([p(f[0]), p(f[1]), p(f[2])], f[3]))
            .collect()
    }

    fn vert(&mut self, p: Vec3) -> u32 {
        self.positions.push(p);
        self.positions.len() as u32 - 1
    }

    /// A grid of 2*n*n triangles on the parallelogram o + s*a + t*b, facing
    /// a x b. Grid points are computed as o + a*(i/n) + b*(j/n), the same
    /// expression for every face, so coincident edges coincide bit for bit.
    pub fn grid(&mut self, o: Vec3, a: Vec3, b: Vec3, n: u32, mat: u32) {
        let base = self.positions.len() as u32;
        for j in 0..=n {
            for i in 0..=n {
                let p = o + a * (i as f32 / n as f32) + b * (j as f32 / n as f32);
                self.vert(p);
            }
        }
        let row = n + 1;
        for j in 0..n {
            for i in 0..n {
                let v = base + j * row + i;
                self.faces.push([v, v + 1, v + row + 1, mat]);
                self.faces.push([v, v + row + 1, v + row, mat]);
            }
        }
    }

    /// Axis-aligned box with outward faces, each face an n x n grid.
    pub fn cuboid(&mut self, lo: Vec3, hi: Vec3, n: u32, mat: u32) {
        let d = hi - lo;
        let (x, y, z) = (Vec3::X * d.x, Vec3::Y * d.y, Vec3::Z * d.z);
        self.grid(lo, z, y, n, mat); // -x
        self.grid(lo + x, y, z, n, mat); // +x
        self.grid(lo, x, z, n, mat); // -y
        self.grid(lo + y, z, x, n, mat); // +y
        self.grid(lo, y, x, n, mat); // -z
        self.grid(lo + z, x, y, n, mat); // +z
    }

    /// Vertical cylinder with `seg` sides and `rings` bands, capped.
    pub fn cylinder(&mut self, base: Vec3, r: f32, h: f32, seg: u32, rings: u32, mat: u32) {
        let start = self.positions.len() as u32;
        for k in 0..=rings {
            let y = h * k as f32 / rings as f32;
            for s in 0..seg {
                let a = std::f32::consts::TAU * s as f32 / seg as f32;
                self.vert(base + Vec3::new(r * a.cos(), y, r * a.sin()));
            }
        }
        for k in 0..rings {
            for s in 0..seg {
                let a = start + k * seg + s;
                let b = start + k * seg + (s + 1) % seg;
                self.faces.push([a, a + seg, b, mat]);
                self.faces.push([b, a + seg, b + seg, mat]);
            }
        }
        let bottom = self.vert(base);
        let top = self.vert(base + Vec3::Y * h);
        for s in 0..seg {
            let a = start + s;
            let b = start + (s + 1) % seg;
            self.faces.push([bottom, b, a, mat]);
            let at = start + rings * seg + s;
            let bt = start + rings * seg + (s + 1) % seg;
            self.faces.push([top, at, bt, mat]);
        }
    }
}

pub const ROOM_MATERIALS: [(&str, [f32; 3], [f32; 3]); 6] = [
    ("wall", [0.70, 0.68, 0.62], [0.0; 3]),
    ("floor", [0.35, 0.30, 0.26], [0.0; 3]),
    ("ceiling", [0.80, 0.80, 0.80], [0.0; 3]),
    ("table", [0.45, 0.28, 0.15], [0.0; 3]),
    ("chair", [0.15, 0.22, 0.45], [0.0; 3]),
    ("panel", [0.0, 0.0, 0.0], [12.0, 11.5, 10.5]),
];

/// [`ROOM_MATERIALS`] as scene materials, indexed like the room's faces.
pub fn room_materials() -> Vec<crate::scene::Material> {
    ROOM_MATERIALS
        .iter()
        .map(|(n, kd, ke)| crate::scene::Material {
            name: n.to_string(),
            albedo: Vec3::from(*kd),
            emission: Vec3::from(*ke),
        })
        .collect()
}

/// The room, in metres: 12 x 3 x 8, y up, a table down the middle with
/// chairs on both sides and two rows of light panels under the ceiling.
pub fn conference_room(p: &RoomParams) -> MeshBuilder {
    let mut m = MeshBuilder::default();
    let (w, h, d) = (12.0f32, 3.0f32, 8.0f32);
    let wall_n = 24;
    // Walls face inward.
    m.grid(Vec3::ZERO, Vec3::Z * d, Vec3::X * w, wall_n, 1); // floor, +y
    m.grid(Vec3::Y * h, Vec3::X * w, Vec3::Z * d, wall_n, 2); // ceiling, -y
    m.grid(Vec3::ZERO, Vec3::X * w, Vec3::Y * h, wall_n, 0); // z = 0, +z
    m.grid(Vec3::Z * d, Vec3::Y * h, Vec3::X * w, wall_n, 0); // z = d, -z
    m.grid(Vec3::ZERO, Vec3::Y * h, Vec3::Z * d, wall_n, 0); // x = 0, +x
    m.grid(Vec3::X * w, Vec3::Z * d, Vec3::Y * h, wall_n, 0); // x = w, -x
    // Table: top and four legs.
    let (t0, t1) = (Vec3::new(2.0, 0.72, 3.0), Vec3::new(10.0, 0.76, 5.0));
    m.cuboid(t0, t1, p.detail * 2, 3);
    for (x, z) in [(2.2, 3.2), (9.8, 3.2), (2.2, 4.8), (9.8, 4.8)] {
        m.cylinder(Vec3::new(x, 0.0, z), 0.05, 0.72, p.leg_segments, 6, 3);
    }
    // Chairs on both sides, facing the table.
    let n = p.chairs_per_side.max(1);
    for side in [0, 1] {
        for i in 0..n {
            let x = 2.4 + (7.2 * (i as f32 + 0.5) / n as f32);
            let (z_seat, back_z) = if side == 0 { (2.35, 2.0) } else { (5.65, 6.0) };
            let seat_lo = Vec3::new(x - 0.23, 0.44, z_seat - 0.23);
            m.cuboid(seat_lo, seat_lo + Vec3::new(0.46, 0.05, 0.46), p.detail, 4);
            let bz: f32 = if side == 0 { back_z } else { back_z - 0.05 };
            m.cuboid(
                Vec3::new(x - 0.23, 0.49, bz),
                Vec3::new(x + 0.23, 1.0, bz + 0.05),
                p.detail,
                4,
            );
            for (dx, dz) in [(-0.2, -0.2), (0.2, -0.2), (-0.2, 0.2), (0.2, 0.2)] {
                m.cylinder(
                    Vec3::new(x + dx, 0.0, z_seat + dz),
                    0.02,
                    0.44,
                    p.leg_segments,
                    8,
                    4,
                );
            }
        }
    }
    // Light panels just under the ceiling, emitting downward.
    for i in 0..4 {
        for j in 0..2 {
            let lo = Vec3::new(2.0 + 2.4 * i as f32, h - 0.01, 2.2 + 2.6 * j as f32);
            m.grid(lo, Vec3::X * 1.2, Vec3::Z * 0.6, 1, 5);
        }
    }
    m
}

/// Writes `<dir>/<name>.obj`, `.mtl` and `.toml`; returns the TOML path and
/// the triangle count.
pub fn write_room(
    dir: &Path,
    name: &str,
    p: &RoomParams,
) -> std::io::Result<(std::path::PathBuf, usize)> {
    std::fs::create_dir_all(dir)?;
    let m = conference_room(p);
    let mut mtl = String::from("# generated by locus gen room\n");
    for (n, kd, ke) in ROOM_MATERIALS {
        let _ = writeln!(mtl, "newmtl {n}\nKd {} {} {}", kd[0], kd[1], kd[2]);
        if ke != [0.0; 3] {
            let _ = writeln!(mtl, "Ke {} {} {}", ke[0], ke[1], ke[2]);
        }
    }
    let mut obj = String::with_capacity(m.faces.len() * 40);
    let _ = writeln!(obj, "# generated by locus gen room\nmtllib {name}.mtl");
    for v in &m.positions {
        let _ = writeln!(obj, "v {} {} {}", v.x, v.y, v.z);
    }
    let mut cur = u32::MAX;
    for f in &m.faces {
        if f[3] != cur {
            cur = f[3];
            let _ = writeln!(obj, "usemtl {}", ROOM_MATERIALS[cur as usize].0);
        }
        let _ = writeln!(obj, "f {} {} {}", f[0] + 1, f[1] + 1, f[2] + 1);
    }
    let toml = format!(
        "# generated by locus gen room\n[camera]\nposition = [0.6, 1.6, 0.6]\nlook_at = [8.0, 0.7, 5.0]\nfov_y = 60.0\nresolution = [{}, {}]\n\n[render]\nspp = {}\nmax_depth = 6\nseed = 7\n\n[octree]\nmax_leaf_tris = 2048\nmax_depth = 6\n\n[[mesh]]\nfile = \"{name}.obj\"\n",
        p.resolution[0], p.resolution[1], p.spp
    );
    std::fs::write(dir.join(format!("{name}.mtl")), mtl)?;
    std::fs::write(dir.join(format!("{name}.obj")), obj)?;
    let tp = dir.join(format!("{name}.toml"));
    std::fs::write(&tp, toml)?;
    Ok((tp, m.faces.len()))
}

/// The white furnace: a closed box of `n` x `n` quads per face, all of one
/// material with albedo `rho` and emission `le`, faces pointing inward.
/// Radiance arriving anywhere from any direction is `le / (1 - rho)`, so a
/// render of it must have that mean whatever the integrator, the farm or
/// the caches do.
pub fn furnace(rho: f32, le: f32, spp: u32, n: u32) -> crate::scene::Scene {
    use crate::scene::{Camera, Material, RenderSettings, Scene};
    let mut mb = MeshBuilder::default();
    let (lo, s) = (Vec3::splat(-1.0), 2.0);
    let (x, y, z) = (Vec3::X * s, Vec3::Y * s, Vec3::Z * s);
    mb.grid(lo, y, z, n, 0); // x = -1, normal +x
    mb.grid(lo + x, z, y, n, 0); // x = +1, normal -x
    mb.grid(lo, z, x, n, 0); // y = -1, normal +y
    mb.grid(lo + y, x, z, n, 0); // y = +1, normal -y
    mb.grid(lo, x, y, n, 0); // z = -1, normal +z
    mb.grid(lo + z, y, x, n, 0); // z = +1, normal -z
    let mats = vec![Material {
        name: "furnace".into(),
        albedo: Vec3::splat(rho),
        emission: Vec3::splat(le),
    }];
    let camera = Camera {
        position: Vec3::new(0.1, -0.2, 0.05),
        look_at: Vec3::new(1.0, 0.3, 0.7),
        up: Vec3::Y,
        fov_y: 90.0,
        width: 24,
        height: 24,
    };
    let settings = RenderSettings {
        spp,
        max_depth: 200,
        seed: 11,
        ..Default::default()
    };
    Scene::from_triangles(
        "<furnace>".into(),
        camera,
        settings,
        mats,
        mb.tagged_triangles(),
    )
}

/// Rays with origins uniform in the scene bounds (shrunk by 5%) and
/// uniform directions: the incoherent case of diffuse interreflection.
pub fn incoherent_rays(prep: &Prepared, n: usize, seed: u64) -> Vec<Ray> {
    let b = crate::geometry::Bounds::of_triangles(&prep.scene.tris);
    let c = b.center();
    let e = b.extent() * 0.45;
    (0..n)
        .map(|i| {
            let k = SampleKey::independent(i as u64, 0, seed);
            let o = c + e * (Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 2.0 - 1.0);
            let z = 1.0 - 2.0 * k.get1d(3);
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = std::f32::consts::TAU * k.get1d(4);
            Ray::new(o, Vec3::new(r * phi.cos(), r * phi.sin(), z))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_room_has_at_least_300k_triangles() {
        let m = conference_room(&RoomParams::default());
        assert!(m.faces.len() >= 300_000, "{} triangles", m.faces.len());
        assert!(m.faces.iter().any(|f| f[3] == 5), "needs light panels");
    }
}
