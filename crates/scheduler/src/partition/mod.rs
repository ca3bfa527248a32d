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
//! units and chooses among the grown, the bisected and the Morton regions;
//! `tests` holds the tests of them all.

use crate::cost::Crossings;
use locus_core::octree::Octree;
use rustc_hash::FxHashMap;

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
    pub fn new(tree: &Octree, crossings: &Crossings) -> Self {
        let n = tree.leaves.len();
        // Per neighbour: (weight either way, weight out of this leaf).
        let mut edges: Vec<FxHashMap<u32, (f64, f64)>> = vec![FxHashMap::default(); n];
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
        // map's own order (which was seeded afresh for every map, and
        // still follows its size and history) drew different regions
        // for the same job from one run to the next.
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
    fn from_maps(edges: Vec<FxHashMap<u32, (f64, f64)>>) -> Self {
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
        let mut edges: Vec<FxHashMap<u32, (f64, f64)>> = vec![FxHashMap::default(); n];
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
mod tests;
