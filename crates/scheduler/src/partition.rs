//! Assigning octree leaves to workers.
//!
//! [`region_growing`] is paper 000, section 2.1: one seed leaf per worker,
//! spread apart; then repeatedly the worker with the least accumulated cost
//! takes the unassigned leaf adjacent to its region with the highest cost;
//! leaves no region can reach go to the least loaded worker. Regions stay
//! compact, so rays cross few region borders. [`morton`] is the baseline:
//! leaves in Morton order (the octree's depth-first order) cut into chunks
//! of equal predicted cost.

use locus_core::octree::Octree;
use std::cmp::Ordering;
use std::collections::BinaryHeap;

#[derive(Clone, Copy, PartialEq)]
struct ByCost(f64, u32);
impl Eq for ByCost {}
impl PartialOrd for ByCost {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for ByCost {
    fn cmp(&self, o: &Self) -> Ordering {
        // Highest cost first; ties to the lower leaf index, so the result is
        // a pure function of the input.
        self.0.total_cmp(&o.0).then(o.1.cmp(&self.1))
    }
}

pub fn region_growing(
    tree: &Octree,
    adjacency: &[Vec<u32>],
    cost: &[f64],
    workers: usize,
) -> Vec<u16> {
    let n = tree.leaves.len();
    let workers = workers.max(1);
    const NONE: u16 = u16::MAX;
    let mut owner = vec![NONE; n];
    if workers == 1 {
        return vec![0; n];
    }
    let center = |l: usize| tree.leaves[l].bounds.center();
    // Seeds: the costliest leaf, then each next seed as far as possible from
    // the seeds so far (farthest-point sampling), preferring leaves with work.
    let has_work: Vec<usize> = (0..n).filter(|&l| cost[l] > 0.0).collect();
    let pool: Vec<usize> = if has_work.len() >= workers {
        has_work
    } else {
        (0..n).collect()
    };
    let mut seeds: Vec<usize> = Vec::with_capacity(workers);
    if let Some(&first) = pool
        .iter()
        .max_by(|&&a, &&b| cost[a].total_cmp(&cost[b]).then(b.cmp(&a)))
    {
        seeds.push(first);
    }
    let mut dist: Vec<f32> = pool
        .iter()
        .map(|&l| center(l).distance_squared(center(seeds[0])))
        .collect();
    while seeds.len() < workers.min(n) {
        let Some((k, _)) = pool
            .iter()
            .enumerate()
            .filter(|(_, l)| !seeds.contains(l))
            .max_by(|a, b| dist[a.0].total_cmp(&dist[b.0]).then(b.0.cmp(&a.0)))
        else {
            break;
        };
        let s = pool[k];
        seeds.push(s);
        for (d, &l) in dist.iter_mut().zip(&pool) {
            *d = d.min(center(l).distance_squared(center(s)));
        }
    }
    let mut load = vec![0.0f64; workers];
    let mut frontier: Vec<BinaryHeap<ByCost>> = (0..workers).map(|_| BinaryHeap::new()).collect();
    for (w, &s) in seeds.iter().enumerate() {
        owner[s] = w as u16;
        load[w] += cost[s];
        for &nb in &adjacency[s] {
            frontier[w].push(ByCost(cost[nb as usize], nb));
        }
    }
    loop {
        // The least loaded worker that can still grow.
        let mut best: Option<usize> = None;
        for w in 0..workers {
            while let Some(&ByCost(_, l)) = frontier[w].peek() {
                if owner[l as usize] == NONE {
                    break;
                }
                frontier[w].pop();
            }
            if !frontier[w].is_empty() && best.is_none_or(|b| load[w] < load[b]) {
                best = Some(w);
            }
        }
        let Some(w) = best else { break };
        let ByCost(c, l) = frontier[w].pop().expect("peeked");
        owner[l as usize] = w as u16;
        load[w] += c;
        for &nb in &adjacency[l as usize] {
            if owner[nb as usize] == NONE {
                frontier[w].push(ByCost(cost[nb as usize], nb));
            }
        }
    }
    // Unreachable leaves, costliest first, to the least loaded worker.
    let mut rest: Vec<usize> = (0..n).filter(|&l| owner[l] == NONE).collect();
    rest.sort_by(|&a, &b| cost[b].total_cmp(&cost[a]).then(a.cmp(&b)));
    for l in rest {
        let w = (0..workers)
            .min_by(|&a, &b| load[a].total_cmp(&load[b]))
            .expect("workers > 0");
        owner[l] = w as u16;
        load[w] += cost[l];
    }
    owner
}

/// Leaves in Morton order split into `workers` chunks of equal predicted
/// cost.
pub fn morton(cost: &[f64], workers: usize) -> Vec<u16> {
    let workers = workers.max(1);
    let total: f64 = cost.iter().sum();
    let mut acc = 0.0;
    cost.iter()
        .map(|&c| {
            // A leaf goes to the chunk its cost midpoint falls in.
            let mid = acc + 0.5 * c;
            acc += c;
            if total > 0.0 {
                ((mid / total * workers as f64) as usize).min(workers - 1) as u16
            } else {
                0
            }
        })
        .collect()
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
    fn region_growing_assigns_every_leaf_and_balances() {
        let t = tree();
        let adj = t.face_neighbours();
        let cost = crate::cost::analytic(&t);
        for w in [1usize, 2, 3, 4, 8] {
            let o = region_growing(&t, &adj, &cost, w);
            assert_eq!(o.len(), t.leaves.len());
            assert!(o.iter().all(|&x| (x as usize) < w));
            let s = loads(&cost, &o, w);
            let max = s.iter().cloned().fold(0.0, f64::max);
            // Greedy growth lands within a few leaves of the mean.
            let biggest = cost.iter().cloned().fold(0.0, f64::max) / cost.iter().sum::<f64>();
            assert!(
                max <= 1.0 / w as f64 + 3.0 * biggest + 0.05,
                "{w} workers: shares {s:?}"
            );
            // Regions are mostly connected: most leaves touch a leaf of their
            // own region.
            if w > 1 {
                let touching = (0..o.len())
                    .filter(|&l| adj[l].iter().any(|&n| o[n as usize] == o[l]))
                    .count();
                assert!(touching as f64 > 0.9 * o.len() as f64);
            }
        }
    }

    #[test]
    fn morton_chunks_are_contiguous_and_even() {
        let t = tree();
        let cost = crate::cost::analytic(&t);
        for w in [1usize, 2, 4, 8] {
            let o = morton(&cost, w);
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
}
