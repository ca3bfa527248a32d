//! Growing regions from seeds (paper 000, section 2.1): one seed per
//! worker, placed by farthest-point sampling and k-means, and regions grown
//! leaf by leaf along the heaviest borders, the worker furthest behind its
//! share of the cost first.

use super::refine::refine;
use super::{LeafGraph, Limits, overflow};
use std::cmp::Ordering;
use std::collections::BinaryHeap;

#[derive(Clone, Copy, PartialEq)]
struct ByAffinity(f64, f64, u32);
impl Eq for ByAffinity {}
impl PartialOrd for ByAffinity {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for ByAffinity {
    fn cmp(&self, o: &Self) -> Ordering {
        // Strongest tie to the region, then highest cost, then the lower
        // leaf index: a pure function of the input.
        self.0
            .total_cmp(&o.0)
            .then(self.1.total_cmp(&o.1))
            .then(o.2.cmp(&self.2))
    }
}

pub(super) fn grow(
    centers: &[glam::Vec3],
    graph: &LeafGraph,
    cost: &[f64],
    lim: &Limits,
) -> Result<Vec<u16>, String> {
    let n = centers.len();
    let workers = lim.targets.len().max(1);
    const NONE: u16 = u16::MAX;
    let mut owner = vec![NONE; n];
    let total: f64 = cost.iter().sum::<f64>().max(f64::MIN_POSITIVE);
    let tie = |l: usize| -> f64 { graph.edges[l].iter().map(|e| e.1).sum::<f64>() + 1e-12 };
    let seeds = seeds(centers, cost, workers);
    let mut load = vec![0.0f64; workers];
    let mut held = vec![0u64; workers];
    let behind = |w: usize, load: &[f64]| load[w] / (lim.targets[w] * total).max(f64::MIN_POSITIVE);
    let mut frontier: Vec<BinaryHeap<ByAffinity>> =
        (0..workers).map(|_| BinaryHeap::new()).collect();
    let push_neighbours =
        |l: usize, w: usize, owner: &[u16], f: &mut Vec<BinaryHeap<ByAffinity>>| {
            for &(nb, _) in &graph.edges[l] {
                let nb = nb as usize;
                if owner[nb] == NONE {
                    let a = graph.weight_to(nb, owner, w as u16) / tie(nb);
                    f[w].push(ByAffinity(a, cost[nb], nb as u32));
                }
            }
        };
    for (w, &s) in seeds.iter().enumerate() {
        if !lim.fits(w, 0, s) {
            continue;
        }
        owner[s] = w as u16;
        load[w] += cost[s];
        held[w] += lim.refs[s];
    }
    for (w, &s) in seeds.iter().enumerate() {
        if owner[s] == w as u16 {
            push_neighbours(s, w, &owner, &mut frontier);
        }
    }
    loop {
        // The worker furthest behind its share that can still grow.
        let mut best: Option<usize> = None;
        for w in 0..workers {
            while let Some(&ByAffinity(_, _, l)) = frontier[w].peek() {
                if owner[l as usize] == NONE && lim.fits(w, held[w], l as usize) {
                    break;
                }
                frontier[w].pop();
            }
            if !frontier[w].is_empty() && best.is_none_or(|b| behind(w, &load) < behind(b, &load)) {
                best = Some(w);
            }
        }
        let Some(w) = best else { break };
        let l = frontier[w].pop().expect("peeked").2 as usize;
        owner[l] = w as u16;
        load[w] += cost[l];
        held[w] += lim.refs[l];
        push_neighbours(l, w, &owner, &mut frontier);
    }
    // Unreached leaves, costliest first, to the worker furthest behind
    // that has room.
    let mut rest: Vec<usize> = (0..n).filter(|&l| owner[l] == NONE).collect();
    rest.sort_by(|&a, &b| cost[b].total_cmp(&cost[a]).then(a.cmp(&b)));
    for l in rest {
        let w = (0..workers)
            .filter(|&w| lim.fits(w, held[w], l))
            .min_by(|&a, &b| behind(a, &load).total_cmp(&behind(b, &load)))
            .ok_or_else(|| overflow(lim, l))?;
        owner[l] = w as u16;
        load[w] += cost[l];
        held[w] += lim.refs[l];
    }
    refine(graph, cost, lim, &mut owner);
    Ok(owner)
}

/// Seeds: farthest-point sampling (the costliest leaf, then each next as
/// far as possible from those so far), moved by a few rounds of
/// cost-weighted k-means (Lloyd) to the leaf nearest each cluster's
/// centre, so that regions grown from them meet along short, straight
/// borders.
fn seeds(centers: &[glam::Vec3], cost: &[f64], workers: usize) -> Vec<usize> {
    let n = centers.len();
    let center = |l: usize| centers[l];
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
    } else {
        return seeds;
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
    // Lloyd rounds with every leaf weighted by its cost (empty leaves a
    // little, so empty space still pulls).
    let weight = |l: usize| cost[l] + 1e-9;
    for _ in 0..8 {
        let k = seeds.len();
        let cs: Vec<glam::Vec3> = seeds.iter().map(|&s| center(s)).collect();
        let mut sum = vec![glam::DVec3::ZERO; k];
        let mut wsum = vec![0.0f64; k];
        for &l in &pool {
            let p = center(l);
            let j = (0..k)
                .min_by(|&a, &b| {
                    p.distance_squared(cs[a])
                        .total_cmp(&p.distance_squared(cs[b]))
                })
                .expect("seeds");
            sum[j] += p.as_dvec3() * weight(l);
            wsum[j] += weight(l);
        }
        let mut next = Vec::with_capacity(k);
        for j in 0..k {
            let c = if wsum[j] > 0.0 {
                (sum[j] / wsum[j]).as_vec3()
            } else {
                cs[j]
            };
            let nearest = pool
                .iter()
                .copied()
                .filter(|l| !next.contains(l))
                .min_by(|&a, &b| {
                    center(a)
                        .distance_squared(c)
                        .total_cmp(&center(b).distance_squared(c))
                        .then(a.cmp(&b))
                })
                .unwrap_or(seeds[j]);
            next.push(nearest);
        }
        if next == seeds {
            break;
        }
        seeds = next;
    }
    seeds
}
