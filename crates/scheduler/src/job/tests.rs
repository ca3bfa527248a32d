//! The job preparation's tests: previews, policies, parts and shares.

use super::*;

/// A worker of one core and no memory budget.
const MEMBER: Member = Member {
    cores: 1,
    budget: 0,
    resident: 0,
};

/// Adds to `scene` a cuboid standing in the Cornell box, each face cut
/// into `n` x `n` quads (12 n^2 triangles of material 0).
fn add_cuboid(scene: &mut Scene, n: u32) {
    let mut m = locus_core::generate::MeshBuilder::default();
    let (lo, hi) = (
        glam::Vec3::new(150.0, 0.0, 150.0),
        glam::Vec3::new(400.0, 300.0, 400.0),
    );
    m.cuboid(lo, hi, n, 0);
    for (t, mat) in m.tagged_triangles() {
        scene.tris.push(t);
        scene.tri_material.push(mat);
    }
}

/// The scene's image in 16-pixel tiles, scanline order.
fn tiles_of(scene: &Scene) -> Vec<locus_core::render::Tile> {
    let c = &scene.camera;
    locus_core::render::tiles(
        c.width,
        c.height,
        16,
        locus_core::render::TileOrder::Scanline,
    )
}

/// The preview runs only where a partition or a rent-or-buy decision
/// needs it: a lone worker holds every leaf, and `fetch` ships the
/// whole scene to every worker that can hold it.
#[test]
fn the_preview_runs_only_where_its_prediction_is_used() {
    let scene = Arc::new(crate::cornell_box());
    let tiles = tiles_of(&scene);
    let rays = |workers: usize, fetch: FetchPolicy| {
        let options = JobOptions {
            fetch,
            ..JobOptions::default()
        };
        let members = vec![MEMBER; workers];
        let p = prepare(scene.clone(), &options, &members, &tiles, &[]).expect("prepared");
        assert_eq!(p.map.owner.len(), p.leaf_tris.len());
        p.preview_rays
    };
    for fetch in [
        FetchPolicy::Forward,
        FetchPolicy::Adaptive,
        FetchPolicy::Fetch,
    ] {
        assert_eq!(rays(1, fetch), 0, "one worker, {fetch:?}");
    }
    assert_eq!(rays(2, FetchPolicy::Fetch), 0);
    assert!(rays(2, FetchPolicy::Forward) > 0);
    assert!(rays(2, FetchPolicy::Adaptive) > 0);
}

/// `adaptive` decides whether to buy on a smaller preview: a job that
/// buys traces fewer preview rays than `forward`'s, and a job that
/// rents then draws its regions from `forward`'s preview, so that they
/// are `forward`'s regions exactly, and counts the rays of both.
#[test]
fn adaptive_decides_on_a_small_preview_and_rents_on_the_full_one() {
    // `forward` asked for its preview by name: under the default it would
    // draw the tiny job's regions without one.
    let job = |scene: &Scene, fetch: FetchPolicy| {
        let options = JobOptions {
            fetch,
            cost_model: CostModel::Sampled,
            ..JobOptions::default()
        };
        let members = [MEMBER; 2];
        prepare(
            Arc::new(scene.clone()),
            &options,
            &members,
            &tiles_of(scene),
            &[],
        )
        .expect("prepared")
    };
    // 256 x 256 pixels at 64 samples: the rays would cost far more
    // than the Cornell box's 32 triangles.
    let scene = crate::cornell_box();
    let (buys, forward) = (
        job(&scene, FetchPolicy::Adaptive),
        job(&scene, FetchPolicy::Forward),
    );
    assert!(buys.replicated);
    assert!(!forward.replicated);
    assert!(
        0 < buys.preview_rays && buys.preview_rays < forward.preview_rays / 2,
        "{} preview rays to decide, {} to draw regions",
        buys.preview_rays,
        forward.preview_rays
    );
    // 64 samples in all, and a cuboid of 2 x 6 x 80^2 triangles in the
    // box: renting is cheaper than shipping, and the decision preview's
    // BVH (parts of 32k) is cut where the full one's is not, so regions
    // drawn from its costs would differ.
    let mut tiny = scene.clone();
    (tiny.camera.width, tiny.camera.height, tiny.settings.spp) = (8, 8, 1);
    add_cuboid(&mut tiny, 80);
    assert!(tiny.tris.len() > 2 * cost::DECISION_PREVIEW.part);
    let (rents, forward) = (
        job(&tiny, FetchPolicy::Adaptive),
        job(&tiny, FetchPolicy::Forward),
    );
    assert!(!rents.replicated);
    assert_eq!(rents.map.owner, forward.map.owner);
    assert!(rents.preview_rays > forward.preview_rays);
}

/// A worker that holds the scene replicated under a memory budget joins
/// its parts as every budgeted worker does, so they are cut by
/// centroid, each triangle in one part, not as runs of whole leaves,
/// which share the triangles of the leaves they both touch and joined
/// traced at 0.55-0.74 of one BVH.
#[test]
fn a_replicated_region_under_a_budget_is_cut_by_centroid() {
    let mut scene = crate::cornell_box();
    add_cuboid(&mut scene, 60);
    let scene = Arc::new(scene);
    let options = JobOptions {
        fetch: FetchPolicy::Fetch,
        ..JobOptions::default()
    };
    let member = |cores| Member {
        cores,
        budget: 48 << 20,
        ..MEMBER
    };
    let p = prepare(
        scene.clone(),
        &options,
        &[member(1), member(3)],
        &tiles_of(&scene),
        &[],
    )
    .expect("prepared");
    assert!(p.replicated);
    // Tiles go to whoever asks: the work is predicted by the cores, not
    // by the partition drawn beside it.
    for (w, share) in [(0, 0.25), (1, 0.75)] {
        assert_eq!(p.predicted_share(w), share);
    }
    for w in 0..2 {
        let parts = &p.parts[w];
        assert!(parts.len() > 1, "worker {w}: {} part", parts.len());
        let mut ids: Vec<u32> = parts.iter().flat_map(|r| r.ids.iter().copied()).collect();
        assert_eq!(
            ids.len(),
            scene.tris.len(),
            "worker {w}: a triangle in two parts"
        );
        ids.sort_unstable();
        ids.dedup();
        assert_eq!(
            ids.len(),
            scene.tris.len(),
            "worker {w}: a triangle in no part"
        );
        assert_eq!(p.region_triangles[w], scene.tris.len() as u64);
    }
}

/// Every part a worker is shipped lists the distinct triangles of its
/// leaves, ascending, and the parts together hold what the worker
/// holds; workers that hold the whole scene share one list per part
/// rather than one copy each.
#[test]
fn parts_list_their_leaves_triangles_once_and_replicas_share_them() {
    let scene = Arc::new(crate::cornell_box());
    let tiles = tiles_of(&scene);
    for (fetch, workers) in [(FetchPolicy::Fetch, 3), (FetchPolicy::Forward, 2)] {
        let options = JobOptions {
            fetch,
            ..JobOptions::default()
        };
        let p = prepare(scene.clone(), &options, &vec![MEMBER; workers], &tiles, &[])
            .expect("prepared");
        assert_eq!(p.replicated, fetch == FetchPolicy::Fetch);
        for w in 0..workers {
            let own: HashMap<u32, &Vec<u32>> =
                p.own_leaves[w].iter().map(|(l, t)| (*l, t)).collect();
            let mut held = Vec::new();
            for run in &p.parts[w] {
                assert!(
                    run.ids.is_sorted_by(|a, b| a < b),
                    "{fetch:?}: not distinct"
                );
                if !p.replicated {
                    let mut want: Vec<u32> = run
                        .leaves
                        .iter()
                        .flat_map(|l| own[l].iter().copied())
                        .collect();
                    want.sort_unstable();
                    want.dedup();
                    assert_eq!(*run.ids, want, "{fetch:?}: worker {w}");
                }
                held.extend(run.ids.iter().copied());
            }
            assert_eq!(held.len() as u64, p.region_triangles[w]);
            if p.replicated {
                held.sort_unstable();
                held.dedup();
                assert_eq!(held.len(), scene.tris.len(), "every triangle, once a part");
                for (a, b) in p.parts[w].iter().zip(&p.parts[0]) {
                    assert!(Arc::ptr_eq(&a.ids, &b.ids), "worker {w} has its own copy");
                }
            }
        }
        // Replicas gather a run's triangles once while a message holds
        // them, and afresh (the same triangles) once none does.
        if p.replicated {
            let (a, b) = (&p.parts[1][0], &p.parts[2][0]);
            let first = a.gather(&scene);
            assert_eq!(*first.ids, *a.ids);
            assert_eq!(first.verts[3], scene.tris[a.ids[3] as usize]);
            let shared = b.gather(&scene);
            assert!(Arc::ptr_eq(&first, &shared), "gathered twice");
            let kept = (*first).clone();
            drop((first, shared));
            let again = b.gather(&scene);
            assert_eq!(*again, kept);
        }
    }
}

/// Rays forwarded among regions: every worker holds the shared
/// leaves as its own (and the camera's among them), and they hold at
/// most the share asked for; with none asked, only the camera's leaf
/// is shared. (Under budgets, `tests/memory.rs` renders with them.)
#[test]
fn shared_leaves_are_every_workers_and_fit_its_budget() {
    let mut scene = crate::cornell_box();
    scene.camera.position = glam::Vec3::new(278.0, 273.0, 250.0);
    let scene = Arc::new(scene);
    let tiles = tiles_of(&scene);
    let tree = octree_for(&scene, 4);
    let camera = cost::camera_leaf(&tree, &scene.camera).expect("inside");
    let all: u64 = tree.leaves.iter().map(|l| l.tris.len() as u64).sum();
    let refs_of = |ls: &[u32]| -> u64 {
        ls.iter()
            .filter(|&&l| l != camera)
            .map(|&l| tree.leaves[l as usize].tris.len() as u64)
            .sum()
    };
    for percent in [0, 10, 40] {
        let mut options = JobOptions {
            fetch: FetchPolicy::Forward,
            ..JobOptions::default()
        };
        options.tuning.shared_percent = percent;
        let p = prepare(scene.clone(), &options, &[MEMBER; 4], &tiles, &[]).expect("prepared");
        assert!(p.shared_leaves.contains(&camera));
        assert!(refs_of(&p.shared_leaves) <= all * percent as u64 / 100);
        if percent == 0 {
            assert_eq!(p.shared_leaves, vec![camera]);
        } else {
            assert!(
                p.shared_leaves.len() > 1,
                "{percent}%: {:?}",
                p.shared_leaves
            );
        }
        for w in 0..4u16 {
            let map = p.map_for(w);
            for &l in &p.shared_leaves {
                assert_eq!(map.owner[l as usize], w);
                assert!(p.own_leaves[w as usize].iter().any(|(o, _)| *o == l));
            }
        }
    }
}

/// The predicted shares a report gives are those the partition
/// balanced: the camera's leaf is every worker's, so its cost counts
/// for none of them (counted for its nominal owner, it made a report
/// predict a quarter of an 8-worker job for a worker that did a
/// tenth).
#[test]
fn predicted_shares_leave_the_shared_camera_leaf_out() {
    let mut scene = crate::cornell_box();
    // Inside the box, low over the floor: the camera's leaf holds
    // triangles, so it has a cost to leave out.
    scene.camera.position = glam::Vec3::new(278.0, 30.0, 250.0);
    scene.camera.look_at = glam::Vec3::new(278.0, 0.0, 262.0);
    let scene = Arc::new(scene);
    let tiles = tiles_of(&scene);
    let options = JobOptions {
        fetch: FetchPolicy::Forward,
        ..JobOptions::default()
    };
    let p = prepare(scene.clone(), &options, &[MEMBER; 4], &tiles, &[]).expect("prepared");
    let tree = octree_for(&scene, 4);
    let leaf = cost::camera_leaf(&tree, &scene.camera).expect("the camera is inside the scene");
    assert!(p.shared_leaves.contains(&leaf));
    let mut cost = cost::analytic(&tree);
    assert!(cost[leaf as usize] > 0.0);
    for &l in &p.shared_leaves {
        cost[l as usize] = 0.0;
    }
    assert_eq!(p.analytic_share, cost::shares(&cost, &p.map.owner, 4));
    let sum: f64 = p.sampled_share.iter().sum();
    assert!((sum - 1.0).abs() < 1e-9, "{:?}", p.sampled_share);
}

/// The job's BVH quality is decided once here, from its settings and
/// its triangle references, and is what every worker's setup carries:
/// `auto` builds quick below one camera sample a triangle and full
/// above, `full` and `quick` hold whatever the samples.
#[test]
fn the_bvh_quality_follows_the_jobs_setting_and_samples() {
    use locus_core::accel::{BuildQuality, BvhSetting};
    // 256 camera samples a pass.
    let quality = |scene: &Scene, bvh: BvhSetting, spp: u32| {
        let mut scene = scene.clone();
        scene.camera.width = 16;
        scene.camera.height = 16;
        scene.settings.spp = spp;
        scene.settings.bvh = bvh;
        let scene = Arc::new(scene);
        let tiles = tiles_of(&scene);
        let options = JobOptions::default();
        let p = prepare(scene, &options, &[MEMBER; 2], &tiles, &[]).expect("prepared");
        let refs: u64 = p.leaf_tris.iter().map(|&n| n as u64).sum();
        (p.bvh_quality, refs)
    };
    let small = crate::cornell_box();
    let mut large = small.clone();
    add_cuboid(&mut large, 8);
    let (_, few) = quality(&small, BvhSetting::Auto, 1);
    let (_, many) = quality(&large, BvhSetting::Auto, 1);
    assert!(few < 256 && many > 256 && many < 16 * 256, "{few} {many}");
    for (scene, bvh, spp, want) in [
        (&small, BvhSetting::Auto, 1, BuildQuality::Full),
        (&large, BvhSetting::Auto, 1, BuildQuality::Quick),
        (&large, BvhSetting::Auto, 16, BuildQuality::Full),
        (&small, BvhSetting::Quick, 16, BuildQuality::Quick),
        (&large, BvhSetting::Full, 1, BuildQuality::Full),
    ] {
        assert_eq!(quality(scene, bvh, spp).0, want, "{bvh:?} at {spp} spp");
    }
}

/// Under the default cost model a job of fewer camera samples than
/// triangle references draws its regions from the small preview, the
/// full one costing it more than it saves; a larger job and one that asks
/// for the sampled model by name trace the full preview, and the analytic
/// model traces none.
#[test]
fn a_job_too_small_for_the_full_preview_draws_from_the_small_one() {
    let mut base = crate::cornell_box();
    add_cuboid(&mut base, 80);
    // Enough pixels that the full preview traces more paths than the
    // small one (each traces at most a path a pixel).
    base.camera.width = 128;
    base.camera.height = 128;
    let run = |spp: u32, fetch: FetchPolicy, model: CostModel| {
        let mut scene = base.clone();
        scene.settings.spp = spp;
        let scene = Arc::new(scene);
        let options = JobOptions {
            fetch,
            cost_model: model,
            ..JobOptions::default()
        };
        let tiles = tiles_of(&scene);
        let p = prepare(scene, &options, &[MEMBER; 2], &tiles, &[]).expect("prepared");
        let refs: u64 = p.leaf_tris.iter().map(|&n| n as u64).sum();
        (p.preview_rays, p.small_preview, refs, p.replicated)
    };
    // 16,384 samples a pass against some 80,000 references: `adaptive`
    // rents.
    let (_, _, refs, _) = run(1, FetchPolicy::Forward, CostModel::Auto);
    assert!(refs > 16384 && refs < 16 * 16384, "{refs} references");
    for fetch in [FetchPolicy::Forward, FetchPolicy::Adaptive] {
        let (small, is_small, _, bought) = run(1, fetch, CostModel::Auto);
        let (full, is_full, _, _) = run(1, fetch, CostModel::Sampled);
        assert!(is_small && !is_full && !bought, "{fetch:?}");
        // `adaptive` traces the small preview to decide on in both.
        assert!(
            0 < small && small < full,
            "{fetch:?}: {small} against {full}"
        );
        let (large, is_small, _, _) = run(16, fetch, CostModel::Auto);
        assert!(!is_small && large >= small, "{fetch:?}: {large}");
    }
    let (large, _, _, _) = run(16, FetchPolicy::Forward, CostModel::Auto);
    let (small, _, _, _) = run(1, FetchPolicy::Forward, CostModel::Auto);
    assert!(large > small, "{large} against {small}");
    assert_eq!(run(1, FetchPolicy::Forward, CostModel::Analytic).0, 0);
    // The small preview asked for by name, where the full one would pay.
    let (asked, is_small, _, _) = run(16, FetchPolicy::Forward, CostModel::Small);
    assert!(is_small && asked == small, "{asked} against {small}");
}
