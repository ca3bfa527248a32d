//! Recursive bisection: a third start for the border smoothing, beside
//! regions grown from seeds and Morton chunks. The units are cut by a
//! plane into two sets whose predicted costs are the two halves' shares
//! of the workers (each unit on the side of its cost midpoint), along the
//! axis whose cut carries the least border weight, and each side is cut
//! again for its own workers. Regions come out as boxes, the most
//! compact shape a cut of the cost can take, which region growing only
//! approaches on some scenes as the workers grow in number.

use super::{LeafGraph, Limits, overflow};
use glam::Vec3;

/// Each unit's worker, or an error when a region holds more triangle
/// references than its worker's memory budget allows (the other starts
/// then stand alone).
pub(super) fn bisect(
    centers: &[Vec3],
    graph: &LeafGraph,
    cost: &[f64],
    lim: &Limits,
) -> Result<Vec<u16>, String> {
    let mut owner = vec![0u16; cost.len()];
    let units: Vec<u32> = (0..cost.len() as u32).collect();
    let workers: Vec<u16> = (0..lim.targets.len().max(1) as u16).collect();
    let mut side = vec![0u8; cost.len()];
    split(
        &Cut {
            centers,
            graph,
            cost,
            targets: lim.targets,
        },
        units,
        &workers,
        &mut side,
        &mut owner,
    );
    let mut held = vec![0u64; workers.len()];
    for (u, &w) in owner.iter().enumerate() {
        held[w as usize] += lim.refs[u];
        if lim.caps[w as usize].is_some_and(|c| held[w as usize] > c) {
            return Err(overflow(lim, u));
        }
    }
    Ok(owner)
}

struct Cut<'a> {
    centers: &'a [Vec3],
    graph: &'a LeafGraph,
    cost: &'a [f64],
    targets: &'a [f64],
}

/// Gives `units` to `workers`, halving both until one worker is left.
/// `side` is scratch, 0 outside each call: while a cut is weighed, the
/// units before it are marked 1 and those after 2, so that only borders
/// between the two count (not those with units cut off earlier).
fn split(c: &Cut, units: Vec<u32>, workers: &[u16], side: &mut [u8], owner: &mut [u16]) {
    if workers.len() == 1 || units.len() <= 1 {
        for &u in &units {
            owner[u as usize] = workers[0];
        }
        return;
    }
    let (lo, hi) = workers.split_at(workers.len() / 2);
    let share = |ws: &[u16]| ws.iter().map(|&w| c.targets[w as usize]).sum::<f64>();
    let frac = share(lo) / (share(lo) + share(hi)).max(f64::MIN_POSITIVE);
    let total: f64 = units.iter().map(|&u| c.cost[u as usize]).sum();
    let mut best: Option<(f64, Vec<u32>, usize)> = None;
    for axis in 0..3 {
        let mut order = units.clone();
        // Ties by index, so that the cut is the same on every run.
        order.sort_by(|&a, &b| {
            let (pa, pb) = (c.centers[a as usize][axis], c.centers[b as usize][axis]);
            pa.total_cmp(&pb).then(a.cmp(&b))
        });
        let at = cut_at(&order, c.cost, frac, total);
        for (i, &u) in order.iter().enumerate() {
            side[u as usize] = if i < at { 1 } else { 2 };
        }
        let weight: f64 = order[..at]
            .iter()
            .flat_map(|&u| c.graph.edges[u as usize].iter())
            .filter(|(b, _)| side[*b as usize] == 2)
            .map(|e| e.1)
            .sum();
        for &u in &order {
            side[u as usize] = 0;
        }
        if best.as_ref().is_none_or(|(w, _, _)| weight < *w) {
            best = Some((weight, order, at));
        }
    }
    let (_, mut order, at) = best.expect("three axes were tried");
    let upper = order.split_off(at);
    split(c, order, lo, side, owner);
    split(c, upper, hi, side, owner);
}

/// Where `order` is cut so that the units before hold `frac` of `total`:
/// each unit goes to the side its cost's midpoint falls on; with no cost
/// at all, by count. Both sides keep at least one unit.
fn cut_at(order: &[u32], cost: &[f64], frac: f64, total: f64) -> usize {
    let at = if total > 0.0 {
        let mut acc = 0.0;
        order
            .iter()
            .position(|&u| {
                let c = cost[u as usize];
                let past = acc + 0.5 * c > frac * total;
                acc += c;
                past
            })
            .unwrap_or(order.len())
    } else {
        (frac * order.len() as f64).round() as usize
    };
    at.clamp(1, order.len() - 1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rustc_hash::FxHashMap as HashMap;

    /// An n x n x 1 grid of unit cells, each joined to its face
    /// neighbours by a border of weight 1.
    fn grid(n: u32) -> (Vec<Vec3>, LeafGraph) {
        let id = |x: u32, y: u32| y * n + x;
        let mut edges: Vec<HashMap<u32, (f64, f64)>> = vec![HashMap::default(); (n * n) as usize];
        for y in 0..n {
            for x in 0..n {
                for (dx, dy) in [(1, 0), (0, 1)] {
                    let (a, b) = (id(x, y), id(x + dx, y + dy));
                    if x + dx < n && y + dy < n {
                        edges[a as usize].insert(b, (1.0, 0.5));
                        edges[b as usize].insert(a, (1.0, 0.5));
                    }
                }
            }
        }
        let centers = (0..n * n)
            .map(|i| Vec3::new((i % n) as f32 + 0.5, (i / n) as f32 + 0.5, 0.5))
            .collect();
        (centers, LeafGraph::from_maps(edges))
    }

    #[test]
    fn four_workers_get_four_quadrants_of_equal_cost() {
        let (centers, graph) = grid(8);
        let cost = vec![1.0; 64];
        let refs = vec![1u64; 64];
        let (targets, caps) = super::super::even(4);
        let lim = Limits {
            targets: &targets,
            caps: &caps,
            refs: &refs,
        };
        let owner = bisect(&centers, &graph, &cost, &lim).unwrap();
        for w in 0..4u16 {
            let cells: Vec<usize> = (0..64).filter(|&u| owner[u] == w).collect();
            assert_eq!(cells.len(), 16, "worker {w}: {cells:?}");
            // A 4 x 4 block: its cells span four columns and four rows.
            let xs: std::collections::BTreeSet<_> = cells.iter().map(|u| u % 8).collect();
            let ys: std::collections::BTreeSet<_> = cells.iter().map(|u| u / 8).collect();
            assert_eq!((xs.len(), ys.len()), (4, 4), "worker {w} is not a quadrant");
        }
        // Two straight cuts of 8 borders each: 16, the least any four
        // regions of 16 cells can have on this grid.
        assert_eq!(graph.cut(&owner), 16.0);
    }

    #[test]
    fn shares_follow_the_workers_targets_and_budgets_are_kept() {
        let (centers, graph) = grid(10);
        // The left half costs three times the right.
        let cost: Vec<f64> = (0..100)
            .map(|u| if u % 10 < 5 { 3.0 } else { 1.0 })
            .collect();
        let refs = vec![1u64; 100];
        let targets = [0.75, 0.25];
        let caps = [None, None];
        let lim = Limits {
            targets: &targets,
            caps: &caps,
            refs: &refs,
        };
        let owner = bisect(&centers, &graph, &cost, &lim).unwrap();
        let total: f64 = cost.iter().sum();
        let first: f64 = (0..100).filter(|&u| owner[u] == 0).map(|u| cost[u]).sum();
        // Within one unit's cost of 3/4.
        assert!(
            (first / total - 0.75).abs() <= 3.0 / total,
            "{first} of {total}"
        );
        let caps = [Some(40), Some(100)];
        let lim = Limits { caps: &caps, ..lim };
        let e = bisect(&centers, &graph, &cost, &lim).unwrap_err();
        assert!(e.contains("memory budgets"), "{e}");
    }
}
