//! Preparing a job on the scheduler: checking the submitted scene, building
//! the octree, predicting leaf costs, partitioning, and cutting out each
//! worker's region geometry.

use crate::{cost, partition};
use locus_core::accel::Accel;
use locus_core::light::LightSet;
use locus_core::octree::Octree;
use locus_core::region::ProcessorMap;
use locus_core::scene::{LoadStats, Scene};
use locus_protocol::control::RegionGeometry;
use locus_protocol::submit::{CostModel, JobRequest, Partitioner};
use std::path::PathBuf;
use std::time::Instant;

pub struct Prepared {
    pub scene: Scene,
    pub map: ProcessorMap,
    pub lights: LightSet,
    pub regions: Vec<RegionGeometry>,
    /// Per worker: its leaves with their triangle lists.
    pub own_leaves: Vec<Vec<(u32, Vec<u32>)>>,
    /// Triangle references per leaf.
    pub leaf_tris: Vec<u32>,
    pub analytic_share: Vec<f64>,
    pub sampled_share: Vec<f64>,
    pub preview_rays: u64,
    pub leaves: u32,
    pub seconds: f64,
}

/// Rejects a request that would make tracing panic or lie.
pub fn validate(req: &JobRequest) -> Result<(), String> {
    if req.tris.len() != req.tri_material.len() {
        return Err(format!(
            "{} triangles but {} material ids",
            req.tris.len(),
            req.tri_material.len()
        ));
    }
    if let Some(i) = req
        .tri_material
        .iter()
        .position(|&m| m as usize >= req.materials.len())
    {
        return Err(format!(
            "triangle {i} names material {}, beyond the {} defined",
            req.tri_material[i],
            req.materials.len()
        ));
    }
    if let Some(i) = req
        .tris
        .iter()
        .position(|t| t.iter().any(|p| !p.is_finite()))
    {
        return Err(format!("triangle {i} has a non-finite vertex"));
    }
    let c = &req.camera;
    if c.width == 0 || c.height == 0 || c.width > 1 << 15 || c.height > 1 << 15 {
        return Err(format!(
            "image size {}x{} is out of range",
            c.width, c.height
        ));
    }
    if !(c.position.is_finite() && c.look_at.is_finite() && c.up.is_finite() && c.fov_y.is_finite())
    {
        return Err("camera has a non-finite value".into());
    }
    let s = &req.settings;
    if s.spp == 0 || s.spp > 1 << 20 {
        return Err(format!("spp {} is out of range", s.spp));
    }
    if s.max_depth > 1024 {
        return Err(format!(
            "max_depth {} is out of range (at most 1024)",
            s.max_depth
        ));
    }
    let o = &req.options;
    if let Some(c) = &o.cache {
        c.check().map_err(|e| format!("cache parameters: {e}"))?;
    }
    if o.tile_size == 0 || o.tuning.packet_size == 0 || o.tuning.max_inflight == 0 {
        return Err("tile size, packet size and max in-flight must be positive".into());
    }
    Ok(())
}

/// The job's octree: the scene's own parameters, refined until there are a
/// few leaves per worker (regions are made of leaves) or leaves hold one
/// triangle.
pub fn octree_for(scene: &Scene, workers: usize) -> Octree {
    let mut params = scene.settings.octree;
    let mut tree = Octree::build(&scene.tris, params);
    while workers > 1 && tree.leaves.len() < 4 * workers && params.max_leaf_tris > 1 {
        params.max_leaf_tris /= 2;
        params.max_depth = params.max_depth.max(8);
        tree = Octree::build(&scene.tris, params);
    }
    tree
}

pub fn prepare(req: &JobRequest, workers: usize) -> Prepared {
    let t = Instant::now();
    let scene = Scene {
        path: PathBuf::from(&req.name),
        camera: req.camera.clone(),
        settings: req.settings.clone(),
        materials: req.materials.clone(),
        tris: req.tris.clone(),
        tri_material: req.tri_material.clone(),
        load_stats: LoadStats::default(),
    };
    let tree = octree_for(&scene, workers);
    let all: Vec<u32> = (0..scene.tris.len() as u32).collect();
    let accel = Accel::build(&scene.tris, &all, scene.magnitude());
    let lights = LightSet::build(&scene);
    let analytic = cost::analytic(&tree);
    let pv = cost::sampled(&scene, &tree, &accel, &lights);
    let chosen = match req.options.cost_model {
        CostModel::Analytic => &analytic,
        CostModel::Sampled => &pv.cost,
    };
    let owner = match req.options.partitioner {
        Partitioner::RegionGrowing => {
            partition::region_growing(&tree, &tree.face_neighbours(), chosen, workers)
        }
        Partitioner::Morton => partition::morton(chosen, workers),
    };
    let regions = (0..workers as u16)
        .map(|w| {
            let ids = ProcessorMap::region_triangles(&tree, &owner, w);
            RegionGeometry {
                verts: ids.iter().map(|&i| scene.tris[i as usize]).collect(),
                material: ids
                    .iter()
                    .map(|&i| scene.tri_material[i as usize])
                    .collect(),
                ids,
            }
        })
        .collect();
    let mut own_leaves = vec![Vec::new(); workers];
    for (i, (l, &o)) in tree.leaves.iter().zip(&owner).enumerate() {
        let mut ids = l.tris.clone();
        ids.sort_unstable();
        own_leaves[o as usize].push((i as u32, ids));
    }
    Prepared {
        leaf_tris: tree.leaves.iter().map(|l| l.tris.len() as u32).collect(),
        own_leaves,
        analytic_share: cost::shares(&analytic, &owner, workers),
        sampled_share: cost::shares(&pv.cost, &owner, workers),
        preview_rays: pv.rays,
        leaves: tree.leaves.len() as u32,
        map: ProcessorMap::new(&tree, owner),
        lights,
        regions,
        scene,
        seconds: t.elapsed().as_secs_f64(),
    }
}
