//! Radiosity as a job of the farm's daemons (`locus submit --kind
//! radiosity`): the scheduler coordinates, the workers are the nodes,
//! linked over loopback sockets, and the solution, its mesh and its image
//! are the one machine's bit for bit, whatever the rings and balancing.

mod common;
use common::runtime;
use locus_core::radiosity::output::{mesh_triangles, render_image};
use locus_core::radiosity::shoot::BvhVisibility;
use locus_core::radiosity::{RadiosityParams, Solver, solve};
use locus_core::render::Prepared;
use locus_core::scene::{Material, Scene};
use locus_protocol::radiosity::{Balance, RadiosityJob};
use locus_protocol::submit::{JobKind, JobOptions, JobRequest};

fn cornell() -> Scene {
    common::small_cornell(32, 24, 1)
}

fn params() -> RadiosityParams {
    RadiosityParams::COARSE
}

const SPP: u32 = 2;

fn request(scene: &Scene, workers: u32, ring: u32, balance: Balance) -> JobRequest {
    let opts = JobOptions {
        workers,
        ..Default::default()
    };
    let mut req = locus_scheduler::client::request(scene, opts);
    req.kind = JobKind::Radiosity(Box::new(RadiosityJob {
        params: params(),
        ring,
        balance,
        spp: SPP,
    }));
    req
}

fn mesh_bits(m: &[[(glam::Vec3, glam::Vec3); 3]]) -> Vec<u32> {
    m.iter()
        .flatten()
        .flat_map(|(p, l)| p.to_array().into_iter().chain(l.to_array()))
        .map(f32::to_bits)
        .collect()
}

#[test]
fn daemons_solve_radiosity_as_one_machine_does_bit_for_bit() {
    let scene = cornell();
    let mut solver = Solver::new(&scene, params()).unwrap();
    let prep = Prepared::new(scene.clone());
    solve(&mut solver, &BvhVisibility(&prep.accel), &mut |_| {});
    let s = &scene.settings;
    let (image, _) = render_image(&solver, &prep.accel, &scene.camera, SPP, s.seed, s.sampler);
    let want_mesh = mesh_bits(&mesh_triangles(&solver));
    let rt = runtime();
    rt.block_on(async {
        // (workers, ring, balance): one ring, rings of 1 and 2 (random
        // polling between rings), a ring of 3.
        for (workers, ring, balance) in [
            (1, 0, Balance::Both),
            (2, 1, Balance::Dynamic),
            (3, 3, Balance::Static),
            (4, 2, Balance::Both),
        ] {
            let farm = locus::farm::LocalFarm::start(workers as usize, 1)
                .await
                .expect("farm");
            let req = request(&scene, workers, ring, balance);
            let r = farm.render(req, &|_, _| {}).await.expect("radiosity job");
            let rad = r.radiosity.as_ref().expect("a radiosity report");
            eprintln!(
                "{workers} workers, rings of {}: {} iterations, {} elements, {} packets, {} by polling",
                rad.ring, rad.iterations, rad.elements, rad.packets, rad.helped
            );
            assert_eq!(rad.nodes, workers);
            assert_eq!(rad.iterations, solver.iterations, "{workers}/{ring}");
            assert_eq!(rad.elements, solver.elements);
            assert_eq!(rad.ledger, solver.ledger());
            assert_eq!(mesh_bits(&rad.mesh), want_mesh, "{workers}/{ring}");
            let got: Vec<u32> = r.pixels.iter().flatten().map(|x| x.to_bits()).collect();
            assert_eq!(got, image.to_bits(), "the image from the solution");
            assert!(rad.packets > 0, "visibility went round in packets");
            assert_eq!(rad.node_times.len(), workers as usize);
            farm.stop().await.expect("clean stop");
        }
    });
}

/// A scene that cannot be solved, and a layout that cannot be cut, fail
/// with their reasons, and the farm runs the next job.
#[test]
fn bad_radiosity_jobs_fail_with_their_reason() {
    let mut dark = cornell();
    for m in &mut dark.materials {
        *m = Material {
            emission: glam::Vec3::ZERO,
            ..m.clone()
        };
    }
    let rt = runtime();
    rt.block_on(async {
        let farm = locus::farm::LocalFarm::start(2, 1).await.expect("farm");
        let e = farm
            .render(request(&dark, 2, 0, Balance::Both), &|_, _| {})
            .await
            .unwrap_err();
        assert!(
            format!("{e:#}").contains("no material emits light"),
            "{e:#}"
        );
        let e = farm
            .render(request(&cornell(), 2, 3, Balance::Both), &|_, _| {})
            .await
            .unwrap_err();
        assert!(
            format!("{e:#}").contains("multiple of the ring length"),
            "{e:#}"
        );
        let r = farm
            .render(request(&cornell(), 2, 2, Balance::None), &|_, _| {})
            .await
            .expect("a good job after the bad ones");
        assert!(r.radiosity.is_some());
        farm.stop().await.expect("clean stop");
    });
}
