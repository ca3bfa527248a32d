//! Benchmarks on the generated ~325k-triangle conference room:
//! BVH build, incoherent closest-hit throughput of locus's tracer against
//! raw obvhs traversal over the same BVH and rays, and path tracing.
//!
//! `cargo bench -p locus-core --bench trace`

use glam::Vec3;
use locus_core::accel::Accel;
use locus_core::generate::{RoomParams, conference_room, incoherent_rays, room_materials};
use locus_core::geometry::Ray;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::{Camera, RenderSettings, Scene};
use locus_core::stats::TraceStats;
use std::sync::OnceLock;

const RAYS: usize = 100_000;

fn room() -> &'static (Prepared, Vec<Ray>, Vec<obvhs::triangle::Triangle>) {
    static ROOM: OnceLock<(Prepared, Vec<Ray>, Vec<obvhs::triangle::Triangle>)> = OnceLock::new();
    ROOM.get_or_init(|| {
        let m = conference_room(&RoomParams::default());
        let (mats, tris) = (room_materials(), m.tagged_triangles());
        let cam = Camera {
            position: Vec3::new(0.6, 1.6, 0.6),
            look_at: Vec3::new(8.0, 0.7, 5.0),
            up: Vec3::Y,
            fov_y: 60.0,
            width: 64,
            height: 48,
        };
        let settings = RenderSettings {
            spp: 2,
            max_depth: 6,
            seed: 7,
            ..Default::default()
        };
        let scene = Scene::from_triangles("room".into(), cam, settings, mats, tris);
        let prep = Prepared::new(scene);
        let rays = incoherent_rays(&prep, RAYS, 1);
        let tris = prep.accel.obvhs_triangles();
        (prep, rays, tris)
    })
}

#[divan::bench(sample_count = 5)]
fn bvh_build(b: divan::Bencher) {
    let (prep, _, _) = room();
    let ids: Vec<u32> = (0..prep.scene.tris.len() as u32).collect();
    b.bench(|| Accel::build(&prep.scene.tris, &ids, prep.scene.magnitude()));
}

#[divan::bench(sample_count = 20)]
fn closest_hit_locus(b: divan::Bencher) {
    let (prep, rays, _) = room();
    b.counter(divan::counter::ItemsCount::new(RAYS)).bench(|| {
        let mut st = TraceStats::default();
        rays.iter()
            .filter(|r| {
                prep.accel
                    .intersect(r, 0.0, f32::INFINITY, &mut st)
                    .is_some()
            })
            .count()
    });
}

#[divan::bench(sample_count = 20)]
fn closest_hit_raw_obvhs(b: divan::Bencher) {
    let (prep, rays, tris) = room();
    b.counter(divan::counter::ItemsCount::new(RAYS)).bench(|| {
        rays.iter()
            .filter(|r| prep.accel.raw_obvhs_closest(tris, r).is_finite())
            .count()
    });
}

#[divan::bench(sample_count = 5)]
fn path_trace_64x48_2spp(b: divan::Bencher) {
    let (prep, _, _) = room();
    let opts = RenderOptions::from_scene(&prep.scene);
    b.counter(divan::counter::ItemsCount::new(64 * 48 * 2usize))
        .bench(|| render(prep, &opts, &|_, _| {}).stats.samples);
}

fn main() {
    divan::main();
}
