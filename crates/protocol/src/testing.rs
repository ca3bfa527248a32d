//! A small job over given triangles, for the tests of the crates that
//! send or receive one (this crate's message tests, the worker's region
//! building). Compiled only with the `testing` feature, which nothing but
//! dev-dependencies turns on.

use crate::control::{JobSetup, MemoryPlan, Tuning};
use crate::submit::FetchPolicy;
use glam::Vec3;
use locus_core::light::LightSet;
use locus_core::octree::{Octree, OctreeParams};
use locus_core::region::ProcessorMap;
use locus_core::scene::{Camera, Material, RenderSettings, Scene};

/// An 8x6 camera five units in front of the origin, looking at it.
pub fn camera() -> Camera {
    Camera {
        position: Vec3::new(0.0, 1.0, 5.0),
        look_at: Vec3::ZERO,
        up: Vec3::Y,
        fov_y: 40.0,
        width: 8,
        height: 6,
    }
}

/// Worker 0's setup of a job over `tris` (one emissive grey material),
/// whose octree leaves go to `workers` workers in turn, leaf `l` to
/// `l % workers`. One sample of depth 3, no caches, `forward`, no memory
/// budget, the region announced as its leaves' triangle count: a caller
/// changes what its test is about with struct update syntax.
pub fn job_setup(tris: &[[Vec3; 3]], workers: u16) -> JobSetup {
    let tree = Octree::build(
        tris,
        OctreeParams {
            max_leaf_tris: 4,
            max_depth: 5,
        },
    );
    let owner: Vec<u16> = (0..tree.leaves.len())
        .map(|l| (l % usize::from(workers.max(1))) as u16)
        .collect();
    let scene = Scene::from_triangles(
        "test".into(),
        camera(),
        RenderSettings::default(),
        vec![Material {
            name: "e".into(),
            albedo: Vec3::splat(0.5),
            emission: Vec3::ONE,
        }],
        tris.iter().map(|&x| (x, 0)).collect(),
    );
    let own_leaves: Vec<(u32, Vec<u32>)> = tree
        .leaves
        .iter()
        .enumerate()
        .filter(|(l, _)| owner[*l] == 0)
        .map(|(l, lf)| (l as u32, lf.tris.clone()))
        .collect();
    JobSetup {
        job: 1,
        me: 0,
        peers: (0..workers)
            .map(|w| format!("127.0.0.1:{}", 4000 + w))
            .collect(),
        camera: camera(),
        spp: 1,
        max_depth: 3,
        seed: 1,
        sampler: locus_core::sampler::Sampler::Sobol,
        materials: scene.materials.clone(),
        lights: LightSet::build(&scene),
        region_triangles: own_leaves.iter().map(|(_, t)| t.len() as u64).sum(),
        own_leaves,
        leaf_tris: tree.leaves.iter().map(|l| l.tris.len() as u32).collect(),
        map: ProcessorMap::new(&tree, owner),
        magnitude: 11.0,
        tuning: Tuning::default(),
        cache: None,
        irradiance: None,
        fetch: FetchPolicy::Forward,
        plan: MemoryPlan {
            budget: 0,
            part_triangles: 1 << 20,
            fetch_bytes: 1 << 20,
            cache_nodes: 0,
        },
        normals: false,
        layout: false,
        bvh_quality: Default::default(),
    }
}
