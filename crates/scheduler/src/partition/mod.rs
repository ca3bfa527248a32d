//! Assigning octree leaves to workers.
//!
//! [`region_growing`] is paper 000, section 2.1 (one seed per worker,
//! regions grown leaf by leaf, the worker furthest behind its share of the
//! cost first), made compact: it grows along, and then smooths, the
//! borders of a [`LeafGraph`] weighted by how many preview rays cross
//! them, since every ray crossing a border between workers is a forwarded
//! query. [`morton`] is the baseline: leaves in Morton order (the octree's
//! depth-first order) cut into chunks of the workers' shares of the
//! predicted cost. Both keep to [`Limits`]: shares by cores, and the
//! triangle references each worker's memory budget allows.
//!
//! `grow` places the seeds and grows regions from them; `bisect` cuts
//! boxes of the cost by planes, a third start; `refine` smooths the
//! borders afterwards; this module builds the leaf graph, cuts leaves into
//! units and chooses among the grown, the bisected and the Morton regions.

use locus_core::octree::Octree;
use std::collections::HashMap;

mod bisect;
mod grow;
mod refine;
use bisect::bisect;
use grow::grow;
pub use refine::FORWARD_COST;
use refine::refine;

/// What every partitioner keeps to: each worker's share of the predicted
/// cost (by its cores, summing to 1) and the most triangle references its
/// memory budget lets it hold (None: no limit).
pub struct Limits<'a> {
    pub targets: &'a [f64],
    pub caps: &'a [Option<u64>],
    /// Triangle references per leaf.
    pub refs: &'a [u64],
}

impl Limits<'_> {
    fn fits(&self, w: usize, held: u64, leaf: usize) -> bool {
        self.caps[w].is_none_or(|c| held + self.refs[leaf] <= c)
    }
}

/// Why leaves could not be placed.
fn overflow(lim: &Limits, leaf: usize) -> String {
    let total: u64 = lim.refs.iter().sum();
    let room: u64 = lim
        .caps
        .iter()
        .map(|c| c.unwrap_or(u64::MAX))
        .fold(0, u64::saturating_add);
    format!(
        "the workers' memory budgets cannot hold the scene: it has {total} triangle references, \
         the budgets allow {room} in all, and leaf {leaf} ({} references) fits no worker's room left; \
         add workers or raise --memory-budget",
        lim.refs[leaf]
    )
}

/// The graph a partition cuts: each leaf's neighbours with the weight of
/// the border between them. Where the cost preview ran, the weight is the
/// number of preview rays that crossed that border (a border between two
/// workers turns each such crossing into a forwarded query), plus a small
/// share by shared face area so that space no preview ray crossed still
/// stays together; without a preview, face area alone.
///
/// Each border also keeps how much of its weight leaves through it
/// (`out`): the sender and the receiver of a forwarded query pay unequal
/// parts of it, so the load a border adds to each side depends on which
/// way its rays go.
pub struct LeafGraph {
    pub edges: Vec<Vec<(u32, f64)>>,
    /// Per edge of `edges`, in the same order: the weight of the crossings
    /// from this leaf into the neighbour (the rest goes the other way; a
    /// border's area share counts half each way).
    pub out: Vec<Vec<f64>>,
}

impl LeafGraph {
    /// The graph of `tree`'s leaves with the preview's `crossings`, per
    /// ordered pair `(from, into)`.
    pub fn new(tree: &Octree, crossings: &HashMap<(u32, u32), u32>) -> Self {
        let n = tree.leaves.len();
        // Per neighbour: (weight either way, weight out of this leaf).
        let mut edges: Vec<HashMap<u32, (f64, f64)>> = vec![HashMap::new(); n];
        let nb = tree.face_neighbours();
        let contact = |a: usize, b: usize| {
            let (p, q) = (&tree.leaves[a].bounds, &tree.leaves[b].bounds);
            let o = (p.max.min(q.max) - p.min.max(q.min)).max(glam::Vec3::ZERO);
            (o.x * o.y + o.y * o.z + o.z * o.x) as f64
        };
        let area_total: f64 = (0..n)
            .flat_map(|a| nb[a].iter().map(move |&b| (a, b as usize)))
            .map(|(a, b)| contact(a, b))
            .sum::<f64>()
            .max(f64::MIN_POSITIVE);
        let traffic: f64 = crossings.values().map(|&c| c as f64).sum();
        // Area carries a twentieth of the traffic's weight, or all of it.
        let area_scale = if traffic > 0.0 {
            0.05 * traffic / area_total
        } else {
            1.0 / area_total
        };
        for a in 0..n {
            for &b in &nb[a] {
                // Face neighbours are listed both ways, so each side of a
                // border adds the area's weight to its own edge; half of
                // it counts as going out of this side.
                let w = contact(a, b as usize) * area_scale;
                let e = edges[a].entry(b).or_default();
                e.0 += w;
                e.1 += 0.5 * w;
            }
        }
        // In a fixed order: a border's weight sums its crossings both
        // ways onto its area's share, and floating-point sums in the
        // map's own order (seeded afresh for every map) drew different
        // regions for the same job from one run to the next.
        let mut crossings: Vec<((u32, u32), u32)> =
            crossings.iter().map(|(&k, &c)| (k, c)).collect();
        crossings.sort_unstable();
        for ((a, b), c) in crossings {
            if (a as usize) < n && (b as usize) < n && a != b {
                let c = c as f64;
                let e = edges[a as usize].entry(b).or_default();
                e.0 += c;
                e.1 += c;
                edges[b as usize].entry(a).or_default().0 += c;
            }
        }
        Self::from_maps(edges)
    }

    /// The graph of per-node neighbour weights (either way, and out of the
    /// node), each list sorted by neighbour so that every walk over it is
    /// deterministic.
    fn from_maps(edges: Vec<HashMap<u32, (f64, f64)>>) -> Self {
        let (edges, out) = edges
            .into_iter()
            .map(|m| {
                let mut v: Vec<(u32, (f64, f64))> = m.into_iter().collect();
                v.sort_by_key(|e| e.0);
                v.into_iter().map(|(b, (w, o))| ((b, w), o)).unzip()
            })
            .unzip();
        Self { edges, out }
    }

    /// Total weight of the borders between different owners.
    pub fn cut(&self, owner: &[u16]) -> f64 {
        let mut c = 0.0;
        for (a, e) in self.edges.iter().enumerate() {
            for &(b, w) in e {
                if (b as usize) > a && owner[a] != owner[b as usize] {
                    c += w;
                }
            }
        }
        c
    }

    /// Weight from `l` into the leaves `owner` gives to `w`.
    fn weight_to(&self, l: usize, owner: &[u16], w: u16) -> f64 {
        self.edges[l]
            .iter()
            .filter(|(b, _)| owner[*b as usize] == w)
            .map(|e| e.1)
            .sum()
    }
}

/// How far above its share of the cost a region may grow while borders
/// are smoothed.
pub const BALANCE_SLACK: f64 = 0.02;
/// Passes of border smoothing.
pub(crate) const REFINE_PASSES: usize = 24;

/// Sizes of partition units tried, as the fraction of the smallest
/// worker's share of the cost and of the references that one unit may
/// hold (0: every leaf a unit). Units are whole octree subtrees: regions
/// made of them have borders that collapse into few route nodes, and
/// coarser units also steer the smoothing, like the coarse levels of a
/// multilevel partitioner, to shorter borders than it finds leaf by leaf.
/// Which size gives the best partition differs from scene to scene (and
/// with the costs: once shading and starting samples were counted, the
/// conference room on two workers found its shortest compact border only
/// with units of a third of a share), so every one is tried (each takes
/// milliseconds).
const UNIT_SIZES: [f64; 10] = [
    1.0 / 3.0,
    1.0 / 4.0,
    1.0 / 5.0,
    1.0 / 6.0,
    1.0 / 8.0,
    1.0 / 10.0,
    1.0 / 12.0,
    1.0 / 16.0,
    1.0 / 32.0,
    0.0,
];

/// What a ray's step from one route node to the next costs against a
/// forwarded query, in the score that picks among partitions. Every ray
/// walks the route of its worker, and a partition whose regions are made
/// of many small subtrees makes every walk longer. Fitted to the engine's
/// CPU time over four partitions of the room on two workers (region
/// growing at three unit sizes and Morton's): a step costs about a
/// thirteenth of a forward.
const ROUTE_STEP_WEIGHT: f64 = 0.08;

/// Paper 000's region growing, made to keep regions compact: one seed
/// unit per worker, spread apart; then repeatedly the worker furthest
/// behind its share of the cost takes the frontier unit most tied to its
/// region (the share of the unit's border weight that the region already
/// holds, then the costliest); units no region reaches go to the worker
/// furthest behind. Then border units move to a neighbouring region
/// wherever that lowers the cut weight and keeps every region within
/// [`BALANCE_SLACK`] of its share. Done for each unit size of
/// [`UNIT_SIZES`]; the partition whose borders and route cost the rays
/// least wins ([`walk_cost`]), unless another's busiest worker is
/// predicted done clearly sooner ([`busiest_load`], [`BALANCE_GAIN`]):
/// coarse units give the shortest borders but cannot always be balanced
/// (at 8 workers on the conference room the shortest border left one
/// worker 1.31 times the mean load, and a border 2% longer 1.16).
pub fn region_growing(
    tree: &Octree,
    graph: &LeafGraph,
    cost: &[f64],
    lim: &Limits,
) -> Result<Vec<u16>, String> {
    use rayon::prelude::*;
    // Every unit size is drawn on its own, so the sizes are drawn side by
    // side (on two cores the room's partition phase took 0.27 s, most of
    // it here and in the preview's counts); the choice among them then
    // goes through them in their order, as one after the other would.
    let drawn: Vec<Result<Candidate, String>> = UNIT_SIZES
        .par_iter()
        .map(|&size| candidate(tree, graph, cost, lim, size))
        .collect();
    choose(drawn)
}

/// One unit size's partition with its two scores.
struct Candidate {
    /// [`walk_cost`].
    walk: f64,
    /// [`busiest_load`].
    busiest: f64,
    owner: Vec<u16>,
}

/// Region growing at one unit size ([`UNIT_SIZES`]), scored.
fn candidate(
    tree: &Octree,
    graph: &LeafGraph,
    cost: &[f64],
    lim: &Limits,
    size: f64,
) -> Result<Candidate, String> {
    let units = Units::new(tree, graph, cost, lim, size);
    let ulim = Limits {
        targets: lim.targets,
        caps: lim.caps,
        refs: &units.refs,
    };
    let owner = partition_units(&units.centers, &units.graph, &units.cost, &ulim)?;
    let owner: Vec<u16> = units.group.iter().map(|&g| owner[g as usize]).collect();
    // The route is collapsed once for both scores.
    let steps = route_steps(tree, graph, &owner);
    Ok(Candidate {
        walk: walk_cost(graph, &owner, steps),
        busiest: busiest_load(graph, cost, lim, &owner, steps),
        owner,
    })
}

/// The shortest walk of the candidates, unless another's busiest worker
/// is predicted done clearly sooner ([`BALANCE_GAIN`]); ties go to the
/// earlier unit size. Without any candidate, the last one's error.
fn choose(drawn: Vec<Result<Candidate, String>>) -> Result<Vec<u16>, String> {
    // The shortest walk, and the soonest done busiest worker, each with
    // its busiest worker's predicted load.
    let mut shortest: Option<(f64, f64, Vec<u16>)> = None;
    let mut soonest: Option<(f64, Vec<u16>)> = None;
    let mut last_err = None;
    for c in drawn {
        let c = match c {
            Ok(c) => c,
            Err(e) => {
                last_err = Some(e);
                continue;
            }
        };
        if soonest.as_ref().is_none_or(|(b, _)| c.busiest < *b) {
            soonest = Some((c.busiest, c.owner.clone()));
        }
        if shortest.as_ref().is_none_or(|(w, _, _)| c.walk < *w) {
            shortest = Some((c.walk, c.busiest, c.owner));
        }
    }
    match (shortest, soonest) {
        (Some((_, short_busiest, short)), Some((busiest, soon))) => {
            Ok(if busiest < (1.0 - BALANCE_GAIN) * short_busiest {
                soon
            } else {
                short
            })
        }
        _ => Err(last_err.unwrap_or_else(|| "no partition".into())),
    }
}

/// How much sooner the busiest worker of a partition must be predicted
/// done than the shortest walk's for region growing to take it over the
/// shortest walk. The predicted loads err by more than small differences:
/// at 4 workers on the conference room (96x72, 4 spp, callgrind) a
/// partition predicted 2.3% sooner done ran its busiest worker 5.8%
/// longer, where at 8 workers predictions 3.3% (room) and 10.6%
/// (conference room) sooner came out 9% and 12% sooner.
const BALANCE_GAIN: f64 = 0.03;

/// What a partition costs the rays that cross its leaves, in the units of
/// the graph's border weights (preview crossings): each crossing between
/// two workers' leaves is a forwarded query, and each crossing between
/// two route nodes a step of the walk ([`ROUTE_STEP_WEIGHT`]), where the
/// route is the octree collapsed by owner (`steps`: [`route_steps`]).
pub fn walk_cost(graph: &LeafGraph, owner: &[u16], steps: f64) -> f64 {
    graph.cut(owner) + ROUTE_STEP_WEIGHT * steps
}

/// The predicted load of a partition's busiest worker against its share
/// of the cores, in the cost's units (the whole job's load had every
/// worker that one's pace): its leaves' cost and its part of the
/// forwards across its borders ([`refine::FORWARD_COST`]), and every
/// worker's walks of its route spread by share ([`ROUTE_STEP_WEIGHT`] of
/// a forward a step; `steps`: [`route_steps`]).
pub fn busiest_load(
    graph: &LeafGraph,
    cost: &[f64],
    lim: &Limits,
    owner: &[u16],
    steps: f64,
) -> f64 {
    refine::busiest(graph, cost, lim, owner) + ROUTE_STEP_WEIGHT * FORWARD_COST * steps
}

/// Preview crossings between leaves in different nodes of the route (the
/// octree collapsed by owner): the steps of the workers' walks.
pub fn route_steps(tree: &Octree, graph: &LeafGraph, owner: &[u16]) -> f64 {
    let (route, _) = tree.collapse(owner);
    // A leaf's centre lies inside it, so it finds the route node that
    // holds the leaf.
    let node: Vec<Option<u32>> = tree
        .leaves
        .iter()
        .map(|l| route.leaf_at(l.bounds.center()))
        .collect();
    let mut steps = 0.0;
    for (a, e) in graph.edges.iter().enumerate() {
        for &(b, w) in e {
            if (b as usize) > a && node[a] != node[b as usize] {
                steps += w;
            }
        }
    }
    steps
}

/// The leaves grouped into partition units, with the units' cost,
/// references, centres and border graph.
struct Units {
    group: Vec<u32>,
    cost: Vec<f64>,
    refs: Vec<u64>,
    centers: Vec<glam::Vec3>,
    graph: LeafGraph,
}

impl Units {
    /// Units of at most `size` of the smallest share (0: leaves).
    fn new(tree: &Octree, graph: &LeafGraph, cost: &[f64], lim: &Limits, size: f64) -> Self {
        let total_cost: f64 = cost.iter().sum();
        let total_refs: f64 = lim.refs.iter().sum::<u64>() as f64;
        let share = lim.targets.iter().cloned().fold(f64::INFINITY, f64::min);
        // Cost and references, each as a fraction of the scene's.
        let weight: Vec<f64> = (0..cost.len())
            .map(|l| {
                let c = if total_cost > 0.0 {
                    cost[l] / total_cost
                } else {
                    0.0
                };
                let r = if total_refs > 0.0 {
                    lim.refs[l] as f64 / total_refs
                } else {
                    0.0
                };
                c + r
            })
            .collect();
        let (group, bounds) = if share.is_finite() && share > 0.0 && size > 0.0 {
            tree.subtree_groups(&weight, share * size)
        } else {
            let all = (0..cost.len() as u32).collect();
            (all, tree.leaves.iter().map(|l| l.bounds).collect())
        };
        let n = bounds.len();
        let (mut ucost, mut refs) = (vec![0.0; n], vec![0u64; n]);
        let mut edges: Vec<HashMap<u32, (f64, f64)>> = vec![HashMap::new(); n];
        for (l, &g) in group.iter().enumerate() {
            ucost[g as usize] += cost[l];
            refs[g as usize] += lim.refs[l];
            for (&(b, w), &o) in graph.edges[l].iter().zip(&graph.out[l]) {
                let h = group[b as usize];
                if h != g {
                    let e = edges[g as usize].entry(h).or_default();
                    e.0 += w;
                    e.1 += o;
                }
            }
        }
        Self {
            group,
            cost: ucost,
            refs,
            centers: bounds.iter().map(|b| b.center()).collect(),
            graph: LeafGraph::from_maps(edges),
        }
    }
}

/// Region growing and smoothing over any units (their centres, border
/// graph and cost): the best of regions grown from seeds, of Morton chunks
/// and of recursive bisection, each smoothed the same way.
fn partition_units(
    centers: &[glam::Vec3],
    graph: &LeafGraph,
    cost: &[f64],
    lim: &Limits,
) -> Result<Vec<u16>, String> {
    let mut best = grow(centers, graph, cost, lim)?;
    // The same balancing and smoothing from Morton's chunks, and from
    // boxes cut by planes: on some scenes and farm sizes an octree cut or
    // a plane is the shorter border to start from. A start that cannot
    // keep the memory budgets is passed over.
    let starts = [morton(cost, lim), bisect(centers, graph, cost, lim)];
    for mut o in starts.into_iter().flatten() {
        refine(graph, cost, lim, &mut o);
        if graph.cut(&o) < graph.cut(&best) {
            best = o;
        }
    }
    Ok(best)
}

/// Leaves in Morton order cut into chunks of the workers' shares of the
/// predicted cost; a chunk ends early where a worker's memory is full.
pub fn morton(cost: &[f64], lim: &Limits) -> Result<Vec<u16>, String> {
    let workers = lim.targets.len().max(1);
    let total: f64 = cost.iter().sum();
    let mut owner = vec![0u16; cost.len()];
    let (mut w, mut acc, mut held) = (0usize, 0.0, 0u64);
    let mut end = lim.targets[0] * total;
    for (l, &c) in cost.iter().enumerate() {
        // A leaf goes to the chunk its cost midpoint falls in.
        while w + 1 < workers && (acc + 0.5 * c > end || !lim.fits(w, held, l)) {
            w += 1;
            held = 0;
            end += lim.targets[w] * total;
        }
        if !lim.fits(w, held, l) {
            return Err(overflow(lim, l));
        }
        owner[l] = w as u16;
        acc += c;
        held += lim.refs[l];
    }
    Ok(owner)
}

/// Even shares for `n` workers, with no memory limit: what the tests and
/// benchmarks of a uniform farm use.
pub fn even(n: usize) -> (Vec<f64>, Vec<Option<u64>>) {
    (vec![1.0 / n.max(1) as f64; n.max(1)], vec![None; n.max(1)])
}

#[cfg(test)]
mod tests {
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
        let graph = LeafGraph::new(&t, &HashMap::new());
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
        let graph = LeafGraph::new(&t, &HashMap::new());
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
        let graph = LeafGraph::new(&t, &HashMap::new());
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

    /// Shares follow the cores, and no region passes its memory cap; a cap
    /// the scene cannot fit under is an error that says why.
    #[test]
    fn shares_follow_cores_and_caps_hold() {
        let t = tree();
        let graph = LeafGraph::new(&t, &HashMap::new());
        let cost = crate::cost::analytic(&t);
        let refs: Vec<u64> = t.leaves.iter().map(|l| l.tris.len() as u64).collect();
        let all: u64 = refs.iter().sum();
        let targets = [0.75, 0.25];
        let caps = [None, None];
        let lim = Limits {
            targets: &targets,
            caps: &caps,
            refs: &refs,
        };
        for o in [
            region_growing(&t, &graph, &cost, &lim).unwrap(),
            morton(&cost, &lim).unwrap(),
        ] {
            let s = loads(&cost, &o, 2);
            assert!((s[0] - 0.75).abs() < 0.06, "{s:?}");
        }
        // Worker 0 may hold only 40% of the references: it gets no more,
        // and worker 1 takes the rest.
        let caps = [Some(all * 4 / 10), None];
        let lim = Limits {
            targets: &targets,
            caps: &caps,
            refs: &refs,
        };
        for o in [
            region_growing(&t, &graph, &cost, &lim).unwrap(),
            morton(&cost, &lim).unwrap(),
        ] {
            let held: u64 = (0..o.len()).filter(|&l| o[l] == 0).map(|l| refs[l]).sum();
            assert!(held <= all * 4 / 10);
        }
        let caps = [Some(all / 3), Some(all / 3)];
        let lim = Limits {
            targets: &targets,
            caps: &caps,
            refs: &refs,
        };
        let e = region_growing(&t, &graph, &cost, &lim).unwrap_err();
        assert!(e.contains("memory budgets"), "{e}");
        assert!(morton(&cost, &lim).is_err());
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
    /// regions, whatever order the map holding them iterates in (every
    /// `HashMap` is seeded afresh): a border's weight sums crossings both
    /// ways onto a fractional area share, which rounds differently in
    /// another order.
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
        for i in 0..32 {
            let map: HashMap<(u32, u32), u32> = list.iter().copied().collect();
            let g = LeafGraph::new(&t, &map);
            assert_eq!(bits(&g), bits(&first), "map {i}");
            assert_eq!(
                region_growing(&t, &g, &cost, &lim).unwrap(),
                owner,
                "map {i}"
            );
        }
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
        let graph = LeafGraph::new(&t, &HashMap::new());
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
}
