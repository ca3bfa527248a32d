//! Scene builders shared by the integration tests.
#![allow(dead_code)]

use glam::Vec3;
use locus_core::generate::MeshBuilder;
use locus_core::scene::{Camera, Material, RenderSettings, Scene};
use std::path::{Path, PathBuf};

pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

pub fn cornell() -> Scene {
    Scene::load(&repo_root().join("scenes/cornell-box/cornell.toml")).expect("cornell box loads")
}

/// The Cornell box at `width` x `height` pixels and `spp` samples a pixel.
pub fn small_cornell(width: u32, height: u32, spp: u32) -> Scene {
    let mut s = cornell();
    s.camera.width = width;
    s.camera.height = height;
    s.settings.spp = spp;
    s
}

pub fn camera(position: Vec3, look_at: Vec3, fov_y: f32, w: u32, h: u32) -> Camera {
    Camera {
        position,
        look_at,
        up: Vec3::Y,
        fov_y,
        width: w,
        height: h,
    }
}

pub fn scene_from(
    mb: &MeshBuilder,
    materials: Vec<Material>,
    camera: Camera,
    settings: RenderSettings,
) -> Scene {
    Scene::from_triangles(
        PathBuf::from("<generated>"),
        camera,
        settings,
        materials,
        mb.tagged_triangles(),
    )
}

/// Icosphere of `level` subdivisions with shared vertices, outward faces.
pub fn icosphere(level: u32, center: Vec3, radius: f32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut v: Vec<Vec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut mid = std::collections::HashMap::new();
        let mut nf = Vec::with_capacity(f.len() * 4);
        let mut midpoint = |a: u32, b: u32, v: &mut Vec<Vec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                v.push(((v[a as usize] + v[b as usize]) * 0.5).normalize());
                v.len() as u32 - 1
            })
        };
        for [a, b, c] in f {
            let ab = midpoint(a, b, &mut v);
            let bc = midpoint(b, c, &mut v);
            let ca = midpoint(c, a, &mut v);
            nf.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = nf;
    }
    (v.into_iter().map(|p| center + p * radius).collect(), f)
}

/// A white furnace: a cube seen from inside, every face wound to point
/// inward (emission is one-sided) with albedo `rho` and emission `le`, each
/// face an n x n grid so NEE samples many triangles. Radiance is
/// Le / (1 - rho) everywhere inside.
pub fn furnace_scene(rho: f32, le: f32, spp: u32, n: u32) -> Scene {
    let scene = locus_core::generate::furnace(rho, le, spp, n);
    // Every face must point inward for the emission to be seen.
    for t in &scene.tris {
        let c = (t[0] + t[1] + t[2]) / 3.0;
        assert!(
            locus_core::geometry::tri_cross(t).dot(-c) > 0.0,
            "face points outward"
        );
    }
    scene
}
