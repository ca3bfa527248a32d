//! The radiosity farm against one machine: whatever the number of nodes,
//! the ring length and the balancing, the solution is the same bits,
//! because the coordinator books receipts in patch order and visibility is
//! the AND of the regions' answers.

use locus_core::octree::{Octree, OctreeParams};
use locus_core::radiosity::shoot::BvhVisibility;
use locus_core::radiosity::{RadiosityParams, Solver, solve, solve_with};
use locus_core::render::Prepared;
use locus_core::scene::Scene;
use locus_worker::radiosity::assign_patches;
use locus_worker::radiosity::coordinator::FarmTimes;
use locus_worker::radiosity::farm::{self, FarmConfig};
use locus_worker::radiosity::node::Layout;
use std::path::Path;
use std::time::Duration;

fn cornell() -> Scene {
    let root = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."));
    Scene::load(&root.join("scenes/cornell-box/cornell.toml")).unwrap()
}

fn params() -> RadiosityParams {
    RadiosityParams::COARSE
}

fn one_machine(scene: &Scene) -> Solver {
    let mut solver = Solver::new(scene, params()).unwrap();
    let prep = Prepared::new(scene.clone());
    solve(&mut solver, &BvhVisibility(&prep.accel), &mut |_| {});
    solver
}

fn on_farm(
    scene: &Scene,
    nodes: u32,
    ring: u32,
    by_elements: bool,
    dynamic: bool,
) -> (Solver, FarmTimes) {
    let mut solver = Solver::new(scene, params()).unwrap();
    let tree = Octree::build(
        &scene.tris,
        OctreeParams {
            max_leaf_tris: 2,
            max_depth: 4,
        },
    );
    // Regions: leaves in Morton order cut into equal runs.
    let leaves = tree.leaves.len();
    let positions: Vec<u16> = (0..leaves)
        .map(|l| (l * ring as usize / leaves) as u16)
        .collect();
    let owner = assign_patches(&solver, nodes, by_elements);
    let cfg = FarmConfig {
        layout: Layout { nodes, ring },
        dynamic,
        seed: 7,
        stall: Duration::from_secs(60),
    };
    let mut farm = farm::start(&mut solver, scene, &tree, &positions, &owner, cfg);
    solve_with(&mut solver, &mut farm, &mut |_| {});
    assert_eq!(farm.error, None, "{nodes} nodes, rings of {ring}");
    (solver, farm.measured)
}

fn assert_same_bits(a: &Solver, b: &Solver, what: &str) {
    assert_eq!(a.iterations, b.iterations, "{what}: iterations");
    assert_eq!(a.elements, b.elements, "{what}: elements");
    assert_eq!(a.patches.len(), b.patches.len());
    for (i, (p, q)) in a.patches.iter().zip(&b.patches).enumerate() {
        assert_eq!(
            p.vertices.len(),
            q.vertices.len(),
            "{what}: patch {i}'s vertices"
        );
        for (v, w) in p.vertices.iter().zip(&q.vertices) {
            for s in 0..2 {
                assert_eq!(
                    v.b[s].to_array().map(f32::to_bits),
                    w.b[s].to_array().map(f32::to_bits),
                    "{what}: patch {i}"
                );
            }
        }
        assert_eq!(p.unshot, q.unshot, "{what}: patch {i}'s unshot radiosity");
    }
    assert_eq!(
        format!("{:?}", a.ledger()),
        format!("{:?}", b.ledger()),
        "{what}: ledger"
    );
}

#[test]
fn the_farm_solution_is_the_one_machine_solution_bit_for_bit() {
    let scene = cornell();
    let reference = one_machine(&scene);
    assert!(
        reference.elements > 200 * 16,
        "adaptive subdivision happened"
    );
    // (nodes, ring length, static, dynamic)
    let layouts = [
        (1, 1, false, false),
        (2, 1, true, true),
        (2, 2, false, false),
        (3, 3, true, false),
        (4, 2, true, true),
        (4, 4, false, true),
        (8, 4, true, true),
        (8, 8, false, false),
    ];
    for (nodes, ring, by_elements, dynamic) in layouts {
        let (farm, measured) = on_farm(&scene, nodes, ring, by_elements, dynamic);
        let what =
            format!("{nodes} nodes in rings of {ring}, static {by_elements}, dynamic {dynamic}");
        assert_same_bits(&reference, &farm, &what);
        assert_eq!(measured.shot_s.len() as u64, farm.iterations, "{what}");
        assert!(measured.packets > 0, "{what}: packets went round");
    }
}

#[test]
fn idle_nodes_take_packets_of_other_rings_only_with_dynamic_balancing() {
    let scene = cornell();
    let (_, without) = on_farm(&scene, 4, 1, false, false);
    assert_eq!(without.helped, 0);
    let (_, with) = on_farm(&scene, 4, 1, false, true);
    assert!(with.helped > 0, "random polling handed packets over");
    let help_s: f64 = with.times.iter().flatten().map(|t| t.helping_s).sum();
    assert!(help_s > 0.0, "helping time is counted");
}

#[test]
fn longer_rings_trace_each_ray_in_every_region_it_crosses() {
    let scene = cornell();
    let (one, _) = on_farm(&scene, 4, 1, true, false);
    let (four, _) = on_farm(&scene, 4, 4, true, false);
    // Every owner a ray's segment crosses traces it against its region.
    assert!(four.stats.shadow_rays > one.stats.shadow_rays);
}
