//! The partitioners' tests: every leaf assigned, shares kept, borders
//! shorter than Morton's, memory budgets kept, and the same regions drawn
//! from the same crossings whatever order they come in.

use super::*;
use glam::Vec3;
use locus_core::octree::OctreeParams;

fn tree() -> Octree {
    let mut tris = Vec::new();
    for i in 0..40 {
        for j in 0..40 {
            let p = Vec3::new(i as f32, j as f32, ((i * 7 + j * 3) % 11) as f32);
            tris.push([p, p + Vec3::X * 0.8, p + Vec3::Z * 0.8]);
        }
    }
    Octree::build(
        &tris,
        OctreeParams {
            max_leaf_tris: 24,
            max_depth: 6,
        },
    )
}

fn loads(cost: &[f64], owner: &[u16], w: usize) -> Vec<f64> {
    crate::cost::shares(cost, owner, w)
}

#[test]
fn region_growing_assigns_every_leaf_balances_and_cuts_less_than_morton() {
    let t = tree();
    let adj = t.face_neighbours();
    let graph = LeafGraph::new(&t, &Crossings::default());
    let cost = crate::cost::analytic(&t);
    let refs: Vec<u64> = t.leaves.iter().map(|l| l.tris.len() as u64).collect();
    for w in [1usize, 2, 3, 4, 8] {
        let (targets, caps) = even(w);
        let lim = Limits {
            targets: &targets,
            caps: &caps,
            refs: &refs,
        };
        let o = region_growing(&t, &graph, &cost, &lim).unwrap();
        assert_eq!(o.len(), t.leaves.len());
        assert!(o.iter().all(|&x| (x as usize) < w));
        let s = loads(&cost, &o, w);
        let max = s.iter().cloned().fold(0.0, f64::max);
        // Growth lands within a few leaves of the share, and smoothing
        // stays within its slack of it.
        let biggest = cost.iter().cloned().fold(0.0, f64::max) / cost.iter().sum::<f64>();
        assert!(
            max <= (1.0 / w as f64) * (1.0 + BALANCE_SLACK) + 3.0 * biggest,
            "{w} workers: shares {s:?}"
        );
        if w > 1 {
            // Regions are connected almost everywhere, and their
            // borders are shorter than Morton's chunks'.
            let touching = (0..o.len())
                .filter(|&l| adj[l].iter().any(|&n| o[n as usize] == o[l]))
                .count();
            assert!(touching as f64 > 0.95 * o.len() as f64);
            let m = morton(&cost, &lim).unwrap();
            eprintln!(
                "{w} workers: cut {} against Morton {}",
                graph.cut(&o),
                graph.cut(&m)
            );
            assert!(
                graph.cut(&o) <= graph.cut(&m),
                "{w}: {} vs {}",
                graph.cut(&o),
                graph.cut(&m)
            );
        }
    }
}

/// One owner costs nothing; a split along the octree's first plane
/// costs its border; leaves dealt out alternately cost far more, in
/// borders and in route steps alike.
#[test]
fn walk_cost_counts_borders_and_route_steps() {
    let t = tree();
    let graph = LeafGraph::new(&t, &Crossings::default());
    let n = t.leaves.len();
    let walk = |o: &[u16]| walk_cost(&graph, o, route_steps(&t, &graph, o));
    assert_eq!(walk(&vec![0; n]), 0.0);
    let half: Vec<u16> = t
        .leaves
        .iter()
        .map(|l| (l.bounds.center().x >= t.bounds.center().x) as u16)
        .collect();
    let dealt: Vec<u16> = (0..n).map(|l| (l % 2) as u16).collect();
    let (h, d) = (walk(&half), walk(&dealt));
    assert!(h > 0.0 && h >= graph.cut(&half));
    assert!(d > 2.0 * h, "{d} vs {h}");
    assert!(d - graph.cut(&dealt) > h - graph.cut(&half), "route steps");
}

/// The busiest worker's predicted load: all of the cost on one worker
/// of an even pair is twice the job at that worker's pace; halves
/// load the busier one with at least its half and its borders'
/// forwards, and a region dealt leaf by leaf pays far more border.
#[test]
fn busiest_load_counts_cost_borders_and_shares() {
    let t = tree();
    let graph = LeafGraph::new(&t, &Crossings::default());
    let cost = crate::cost::analytic(&t);
    let total: f64 = cost.iter().sum();
    let n = t.leaves.len();
    let refs = vec![1u64; n];
    let (targets, caps) = even(2);
    let lim = Limits {
        targets: &targets,
        caps: &caps,
        refs: &refs,
    };
    let load = |o: &[u16]| busiest_load(&graph, &cost, &lim, o, route_steps(&t, &graph, o));
    let one = load(&vec![0; n]);
    assert!(
        (one - 2.0 * total).abs() <= 1e-9 * total,
        "{one} vs {total}"
    );
    let half: Vec<u16> = t
        .leaves
        .iter()
        .map(|l| (l.bounds.center().x >= t.bounds.center().x) as u16)
        .collect();
    let h = load(&half);
    let shares = crate::cost::shares(&cost, &half, 2);
    let larger = shares[0].max(shares[1]) * total / 0.5;
    assert!(
        h > larger && h < one,
        "{h}: cost alone {larger}, one worker {one}"
    );
    let dealt: Vec<u16> = (0..n).map(|l| (l % 2) as u16).collect();
    assert!(load(&dealt) > h);
}

/// Region growing's and Morton's partitions of `t` under these shares,
/// caps and references.
fn both(
    t: &Octree,
    graph: &LeafGraph,
    cost: &[f64],
    refs: &[u64],
    targets: &[f64],
    caps: &[Option<u64>],
) -> [Result<Vec<u16>, String>; 2] {
    let lim = Limits {
        targets,
        caps,
        refs,
    };
    [region_growing(t, graph, cost, &lim), morton(cost, &lim)]
}

/// Shares follow the cores, and no region passes its memory cap; a cap
/// the scene cannot fit under is an error that says why.
#[test]
fn shares_follow_cores_and_caps_hold() {
    let t = tree();
    let graph = LeafGraph::new(&t, &Crossings::default());
    let cost = crate::cost::analytic(&t);
    let refs: Vec<u64> = t.leaves.iter().map(|l| l.tris.len() as u64).collect();
    let all: u64 = refs.iter().sum();
    let targets = [0.75, 0.25];
    for o in both(&t, &graph, &cost, &refs, &targets, &[None, None]) {
        let s = loads(&cost, &o.unwrap(), 2);
        assert!((s[0] - 0.75).abs() < 0.06, "{s:?}");
    }
    // Worker 0 may hold only 40% of the references: it gets no more,
    // and worker 1 takes the rest.
    let caps = [Some(all * 4 / 10), None];
    for o in both(&t, &graph, &cost, &refs, &targets, &caps) {
        let o = o.unwrap();
        let held: u64 = (0..o.len()).filter(|&l| o[l] == 0).map(|l| refs[l]).sum();
        assert!(held <= all * 4 / 10);
    }
    let caps = [Some(all / 3), Some(all / 3)];
    let [grown, chunks] = both(&t, &graph, &cost, &refs, &targets, &caps);
    let e = grown.unwrap_err();
    assert!(e.contains("memory budgets"), "{e}");
    assert!(chunks.is_err());
}

#[test]
fn morton_chunks_are_contiguous_and_even() {
    let t = tree();
    let cost = crate::cost::analytic(&t);
    let refs: Vec<u64> = t.leaves.iter().map(|l| l.tris.len() as u64).collect();
    for w in [1usize, 2, 4, 8] {
        let (targets, caps) = even(w);
        let lim = Limits {
            targets: &targets,
            caps: &caps,
            refs: &refs,
        };
        let o = morton(&cost, &lim).unwrap();
        assert!(
            o.windows(2).all(|p| p[0] <= p[1]),
            "chunks follow leaf order"
        );
        let s = loads(&cost, &o, w);
        let biggest = cost.iter().cloned().fold(0.0, f64::max) / cost.iter().sum::<f64>();
        for x in s {
            assert!((x - 1.0 / w as f64).abs() <= biggest + 1e-9);
        }
    }
}

/// The same crossings give the same graph, to the bit, and the same
/// regions, whatever order the map holding them iterates in: a border's
/// weight sums crossings both ways onto a fractional area share, which
/// rounds differently in another order. The maps are filled from
/// rotations of one list into tables of different sizes, which iterate
/// in different orders (checked), so the graph must not follow them.
#[test]
fn the_same_crossings_draw_the_same_regions() {
    let t = tree();
    let nb = t.face_neighbours();
    let mut list = Vec::new();
    for (a, ns) in nb.iter().enumerate() {
        for &b in ns {
            let (a, b) = (a as u32, b);
            // Both ways, of unequal and uneven counts.
            list.push(((a, b), 1 + (a * 7919 + b * 104_729) % 100_003));
        }
    }
    let cost = crate::cost::analytic(&t);
    let refs: Vec<u64> = t.leaves.iter().map(|l| l.tris.len() as u64).collect();
    let (targets, caps) = even(4);
    let lim = Limits {
        targets: &targets,
        caps: &caps,
        refs: &refs,
    };
    let bits = |g: &LeafGraph| -> Vec<(u32, u64, u64)> {
        g.edges
            .iter()
            .zip(&g.out)
            .flat_map(|(e, o)| {
                e.iter()
                    .zip(o)
                    .map(|(&(b, w), o)| (b, w.to_bits(), o.to_bits()))
            })
            .collect()
    };
    let first = LeafGraph::new(&t, &list.iter().copied().collect());
    let owner = region_growing(&t, &first, &cost, &lim).unwrap();
    let mut orders = std::collections::HashSet::new();
    for i in 0..32 {
        let mut map =
            Crossings::with_capacity_and_hasher(list.len() << (i % 4), Default::default());
        let rotated = list.iter().cycle().skip(i * 37 % list.len());
        map.extend(rotated.take(list.len()).copied());
        orders.insert(map.keys().copied().collect::<Vec<_>>());
        let g = LeafGraph::new(&t, &map);
        assert_eq!(bits(&g), bits(&first), "map {i}");
        assert_eq!(
            region_growing(&t, &g, &cost, &lim).unwrap(),
            owner,
            "map {i}"
        );
    }
    assert!(orders.len() > 1, "every map iterated in one order");
}

/// The unit sizes' candidates are chosen among in their order: the
/// shortest walk (the earlier of equal ones), unless another's busiest
/// worker is predicted done more than [`BALANCE_GAIN`] sooner; failed
/// sizes are passed over, and with none left the last error is said.
#[test]
fn candidates_are_chosen_in_order_of_unit_size() {
    let c = |walk: f64, busiest: f64, tag: u16| -> Result<Candidate, String> {
        Ok(Candidate {
            walk,
            busiest,
            owner: vec![tag],
        })
    };
    let err = |e: &str| -> Result<Candidate, String> { Err(e.into()) };
    // Equal walks: the earlier size.
    assert_eq!(choose(vec![c(5.0, 1.0, 1), c(5.0, 1.0, 2)]), Ok(vec![1]));
    // The shorter walk, wherever it stands, past an error.
    assert_eq!(
        choose(vec![c(5.0, 1.0, 1), err("a"), c(4.0, 1.0, 3)]),
        Ok(vec![3])
    );
    // A busiest worker done 2% sooner does not outweigh a shorter walk;
    // 5% sooner does (the earliest of the soonest).
    assert_eq!(choose(vec![c(4.0, 1.0, 1), c(9.0, 0.98, 2)]), Ok(vec![1]));
    assert_eq!(
        choose(vec![c(4.0, 1.0, 1), c(9.0, 0.95, 2), c(8.0, 0.95, 3)]),
        Ok(vec![2])
    );
    assert_eq!(choose(vec![err("a"), err("b")]), Err("b".into()));
    assert_eq!(choose(Vec::new()), Err("no partition".into()));
}

/// Drawn side by side, the sizes give what drawing them one after the
/// other gives, at every farm size.
#[test]
fn sizes_drawn_side_by_side_give_the_sequential_choice() {
    let t = tree();
    let graph = LeafGraph::new(&t, &Crossings::default());
    let cost = crate::cost::analytic(&t);
    let refs: Vec<u64> = t.leaves.iter().map(|l| l.tris.len() as u64).collect();
    for w in [2usize, 3, 5, 8] {
        let (targets, caps) = even(w);
        let lim = Limits {
            targets: &targets,
            caps: &caps,
            refs: &refs,
        };
        let one_by_one = UNIT_SIZES
            .iter()
            .map(|&size| candidate(&t, &graph, &cost, &lim, size))
            .collect();
        assert_eq!(
            region_growing(&t, &graph, &cost, &lim),
            choose(one_by_one),
            "{w} workers"
        );
    }
}
