//! Smoothing region borders: leaves move to the neighbouring region that
//! cuts the least border weight, within each region's share of the cost
//! (border crossings counted as work) and its memory.

use super::{BALANCE_SLACK, LeafGraph, Limits, REFINE_PASSES};

/// What a forwarded query costs its sender and receiver beyond the
/// tracing the cost preview counts (sending it, its answer coming back and
/// its slot answered; decoding it, walking the route again, restarting a
/// BVH traversal, answering), in the preview's units of BVH steps (about
/// 28 instructions, see `cost::VERTEX_COST`): 2,163 instructions to
/// forward and 1,710 to receive in `crates/locus/src/bench/fit_costs.py`'s
/// fit over 36 workers of 8 `forward_cost.py` runs (room and conference
/// room, 2 to 8 workers), a worker's BVH step held at the 76 instructions
/// of the fit before. That fit (813 and 1,676, charged 90 steps with a
/// third to the sender) counted no instruction of the async runtime's
/// worker threads, where packets are read, decoded and written: counted
/// whole, a query costs more, and more of it falls on its sender. A
/// region's load is its leaves' cost plus, for every preview crossing of
/// its border, the sender's part of this ([`SENDER_SHARE`]) where the ray
/// leaves it and the receiver's where it enters: borders make work.
/// Recharged so, the room's busiest worker (`forward_cost.py`, one thread
/// a worker) did 3.2%, 6.7% and 3.7% less at 2, 4 and 8 workers, and the
/// conference room's partitions did not change.
pub const FORWARD_COST: f64 = 140.0;

/// The sender's part of [`FORWARD_COST`] (2,163 of 2,163 + 1,710
/// instructions); the receiver pays the rest. Where a border's rays go
/// mostly one way (out of the region that starts the camera samples), the
/// side they leave does more of its work.
pub const SENDER_SHARE: f64 = 2163.0 / (2163.0 + 1710.0);

/// Loads that count borders: cost plus each region's part of
/// [`FORWARD_COST`] for the weight crossing its border, kept up to date
/// leaf move by leaf move.
struct Loads<'a> {
    graph: &'a LeafGraph,
    cost: &'a [f64],
    load: Vec<f64>,
    held: Vec<u64>,
}

/// What the border between a leaf and its `i`-th neighbour loads the
/// leaf's region with, and the neighbour's, when they differ.
#[inline]
fn border_loads(graph: &LeafGraph, l: usize, i: usize) -> (f64, f64) {
    let w = graph.edges[l][i].1;
    let out = graph.out[l][i];
    let (send, recv) = (
        SENDER_SHARE * FORWARD_COST,
        (1.0 - SENDER_SHARE) * FORWARD_COST,
    );
    (send * out + recv * (w - out), recv * out + send * (w - out))
}

impl<'a> Loads<'a> {
    fn new(graph: &'a LeafGraph, cost: &'a [f64], lim: &Limits, owner: &[u16]) -> Self {
        let w = lim.targets.len().max(1);
        let (mut load, mut held) = (vec![0.0; w], vec![0u64; w]);
        for (l, &o) in owner.iter().enumerate() {
            load[o as usize] += cost[l];
            held[o as usize] += lim.refs[l];
            for (i, &(b, _)) in graph.edges[l].iter().enumerate() {
                if owner[b as usize] != o {
                    load[o as usize] += border_loads(graph, l, i).0;
                }
            }
        }
        Self {
            graph,
            cost,
            load,
            held,
        }
    }

    /// The loads of regions `a` and `b` if leaf `l` moved from `a` to `b`.
    fn after_move(&self, owner: &[u16], l: usize, b: usize) -> (f64, f64) {
        let a = owner[l] as usize;
        let (mut la, mut lb) = (self.load[a] - self.cost[l], self.load[b] + self.cost[l]);
        for (i, &(n, _)) in self.graph.edges[l].iter().enumerate() {
            let o = owner[n as usize] as usize;
            // What the border loads l's side with, and n's.
            let (mine, theirs) = border_loads(self.graph, l, i);
            if o == a {
                // Internal to a, now a border of both.
                la += theirs;
                lb += mine;
            } else if o == b {
                // A border of both, now internal to b.
                la -= mine;
                lb -= theirs;
            } else {
                // A border of a with c, now of b with c.
                la -= mine;
                lb += mine;
            }
        }
        (la, lb)
    }

    fn apply(&mut self, owner: &mut [u16], lim: &Limits, l: usize, b: usize) {
        let a = owner[l] as usize;
        let (la, lb) = self.after_move(owner, l, b);
        self.load[a] = la;
        self.load[b] = lb;
        self.held[a] -= lim.refs[l];
        self.held[b] += lim.refs[l];
        owner[l] = b as u16;
    }
}

/// Border smoothing (after Fiduccia and Mattheyses, greedy), on loads that
/// count borders ([`FORWARD_COST`]). First balance: while a region is above
/// its share plus [`BALANCE_SLACK`], its border leaf whose move costs the
/// least cut goes to the neighbour with the most room. Then smooth: a leaf
/// moves to the neighbouring region it is most tied to when that lowers
/// the cut and both regions stay within their shares plus or minus the
/// slack (and their memory).
pub(super) fn refine(graph: &LeafGraph, cost: &[f64], lim: &Limits, owner: &mut [u16]) {
    let workers = lim.targets.len();
    if workers < 2 {
        return;
    }
    let mut loads = Loads::new(graph, cost, lim, owner);
    let total: f64 = loads.load.iter().sum();
    let cap = |w: usize| lim.targets[w] * total * (1.0 + BALANCE_SLACK);
    // A region gives leaves away only down to its share less the slack:
    // where borders are dear, moving a small region's leaves to its
    // neighbours cuts the most border of all, down to a worker with
    // nothing to do.
    let floor = |w: usize| lim.targets[w] * total * (1.0 - BALANCE_SLACK);
    let neighbours = |l: usize, owner: &[u16]| {
        let mut v: Vec<usize> = graph.edges[l]
            .iter()
            .map(|&(n, _)| owner[n as usize] as usize)
            .filter(|&o| o != owner[l] as usize)
            .collect();
        v.sort_unstable();
        v.dedup();
        v
    };
    // Balance.
    for _ in 0..owner.len() {
        let Some(a) = (0..workers)
            .filter(|&w| loads.load[w] > cap(w))
            .max_by(|&x, &y| (loads.load[x] / cap(x)).total_cmp(&(loads.load[y] / cap(y))))
        else {
            break;
        };
        let mut best: Option<(f64, usize, usize)> = None;
        for l in (0..owner.len()).filter(|&l| owner[l] as usize == a) {
            for b in neighbours(l, owner) {
                let (la, lb) = loads.after_move(owner, l, b);
                if lb > cap(b) || la >= loads.load[a] || !lim.fits(b, loads.held[b], l) {
                    continue;
                }
                // Cut change of the move: what joins b minus what leaves a.
                let dcut =
                    graph.weight_to(l, owner, a as u16) - graph.weight_to(l, owner, b as u16);
                if best.is_none_or(|(d, _, _)| dcut < d) {
                    best = Some((dcut, l, b));
                }
            }
        }
        let Some((_, l, b)) = best else { break };
        loads.apply(owner, lim, l, b);
    }
    // Smooth.
    for _ in 0..REFINE_PASSES {
        let mut moved = 0;
        for l in 0..owner.len() {
            let a = owner[l] as usize;
            let here = graph.weight_to(l, owner, a as u16);
            let mut best: Option<(f64, usize)> = None;
            for b in neighbours(l, owner) {
                let gain = graph.weight_to(l, owner, b as u16) - here;
                if gain <= 1e-12 || best.is_some_and(|(g, _)| gain <= g) {
                    continue;
                }
                let (la, lb) = loads.after_move(owner, l, b);
                if lb <= cap(b).max(loads.load[b])
                    && la <= cap(a).max(loads.load[a])
                    && la >= floor(a).min(loads.load[a])
                    && lim.fits(b, loads.held[b], l)
                {
                    best = Some((gain, b));
                }
            }
            if let Some((_, b)) = best {
                loads.apply(owner, lim, l, b);
                moved += 1;
            }
        }
        if moved == 0 {
            break;
        }
    }
}

/// The most loaded region's load (its leaves' cost and its part of its
/// borders' forwards, see [`Loads`]) over its share of the cores.
pub(super) fn busiest(graph: &LeafGraph, cost: &[f64], lim: &Limits, owner: &[u16]) -> f64 {
    let loads = Loads::new(graph, cost, lim, owner);
    (0..loads.load.len())
        .map(|w| loads.load[w] / lim.targets[w])
        .fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rustc_hash::FxHashMap as HashMap;

    /// Two equal regions of one leaf each with a busy border between them:
    /// giving one leaf to the other region would end the border, and the
    /// loads its crossings added would leave room for it, but it would
    /// also leave a worker with nothing to do.
    #[test]
    fn smoothing_leaves_no_region_below_its_share() {
        let edges: Vec<HashMap<u32, (f64, f64)>> = vec![
            [(1, (10.0, 5.0))].into_iter().collect(),
            [(0, (10.0, 5.0))].into_iter().collect(),
        ];
        let graph = LeafGraph::from_maps(edges);
        let cost = [100.0, 100.0];
        let lim = Limits {
            targets: &[0.5, 0.5],
            caps: &[None, None],
            refs: &[1, 1],
        };
        // The border's crossings load each side more than a leaf costs.
        const { assert!(0.5 * FORWARD_COST * 10.0 > 100.0) };
        let mut owner = [0u16, 1];
        refine(&graph, &cost, &lim, &mut owner);
        assert_eq!(owner, [0, 1]);
    }
}
