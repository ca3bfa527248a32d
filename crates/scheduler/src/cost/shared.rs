//! What every worker holds beside its region: the leaves a preview's rays
//! cross most per triangle ([`shared_leaves`]), and the crossings that are
//! left once those are passed over ([`Preview::crossings_beside`]), along
//! which regions are grown (`job::regions`).

use super::{Preview, WALK_END};
use std::collections::HashMap;

impl Preview {
    /// The crossings as the preview would have counted them had the
    /// `shared` leaves (which every worker holds, so that no query is
    /// forwarded into them) been passed over like the camera's: a ray
    /// from leaf `a` through shared leaves into leaf `b` crosses from `a`
    /// into `b`. With none shared, [`Preview::crossings`] to the count.
    pub fn crossings_beside(&self, shared: &[bool]) -> HashMap<(u32, u32), u32> {
        let mut out: HashMap<(u32, u32), u32> = HashMap::new();
        let mut prev: Option<u32> = None;
        for &l in &self.walks {
            if l == WALK_END {
                prev = None;
                continue;
            }
            if shared.get(l as usize).copied().unwrap_or(false) {
                continue;
            }
            match prev.replace(l) {
                Some(p) if p != l => *out.entry((p, l)).or_default() += 1,
                _ => {}
            }
        }
        out
    }
}

/// Crossings into or out of each of `n` leaves.
fn traffic(crossings: &HashMap<(u32, u32), u32>, n: usize) -> Vec<u64> {
    let mut t = vec![0u64; n];
    for (&(a, b), &c) in crossings {
        t[a as usize] += c as u64;
        t[b as usize] += c as u64;
    }
    t
}

/// Leaves worth giving every worker beside its region (beside those
/// `shared` already), holding at most `most` triangle references in all:
/// those the preview's paths cross into or out of most often per
/// triangle they hold. Paper 000's hybrid scheduling in the partition's
/// terms: a ray is never forwarded into a leaf every worker holds, so the
/// few triangles that most rays meet (walls, floors, a room's large
/// surfaces) are traced by whoever holds the ray, demand-driven, and only
/// the detailed rest is data-parallel. On the room with 2 workers, a
/// tenth of the triangles shared cut forwarded queries from 0.275 to
/// 0.066 a ray, on the conference room from 0.251 to 0.039 (the README's
/// "Shared leaves").
pub fn shared_leaves(
    refs: &[u64],
    crossings: &HashMap<(u32, u32), u32>,
    shared: &[bool],
    most: u64,
) -> Vec<u32> {
    let traffic = traffic(crossings, refs.len());
    let mut order: Vec<u32> = (0..refs.len() as u32)
        .filter(|&l| !shared[l as usize] && traffic[l as usize] > 0)
        .collect();
    // Per triangle, with a few more counted than a leaf holds, so that a
    // leaf of one or two triangles that a handful of rays cross does not
    // outrank a wall every path meets.
    let score = |l: u32| traffic[l as usize] as f64 / (refs[l as usize] + 16) as f64;
    order.sort_by(|&a, &b| score(b).total_cmp(&score(a)).then(a.cmp(&b)));
    let mut used = 0;
    let mut out = Vec::new();
    for l in order {
        let r = refs[l as usize];
        if used + r > most {
            continue;
        }
        used += r;
        out.push(l);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::tests::{Cornell, cornell_preview};
    use super::*;

    /// The preview's walks count its crossings again: the same to the
    /// count with nothing shared, and with a leaf shared, none into or out
    /// of it, every other crossing kept, and the ones through it joined
    /// up (as many as went into it and on to another leaf).
    #[test]
    fn crossings_beside_shared_leaves_join_what_went_through_them() {
        let Cornell { tree, pv, .. } = cornell_preview(8, 4);
        let n = tree.leaves.len();
        assert_eq!(pv.crossings_beside(&vec![false; n]), pv.crossings);
        // The leaf crossed most.
        let through = traffic(&pv.crossings, n);
        let s = (0..n).max_by_key(|&l| through[l]).expect("leaves");
        let mut shared = vec![false; n];
        shared[s] = true;
        let beside = pv.crossings_beside(&shared);
        let s = s as u32;
        assert!(beside.keys().all(|&(a, b)| a != s && b != s));
        let mut joined = 0;
        for (&(a, b), &c) in &beside {
            let before = pv.crossings.get(&(a, b)).copied().unwrap_or(0);
            assert!(c >= before, "{a} -> {b}: {c} against {before}");
            joined += c - before;
        }
        assert!(joined > 0, "no crossing went through leaf {s}");
        let into: u32 = pv
            .crossings
            .iter()
            .filter(|((_, b), _)| *b == s)
            .map(|(_, c)| c)
            .sum();
        assert!(joined <= into);
    }

    /// Leaves are shared by crossings per triangle, best first, as many
    /// as fit in `most` references; none already shared is picked again.
    #[test]
    fn shared_leaves_are_the_most_crossed_per_triangle_that_fit() {
        let refs = [10, 1000, 10, 0, 50, 4];
        let crossings: HashMap<(u32, u32), u32> = [
            ((0, 1), 100),
            ((1, 2), 100),
            ((2, 4), 5),
            ((0, 2), 50),
            ((5, 1), 1),
        ]
        .into();
        // Crossings per (triangle + 16): leaf 2 155/26, leaf 0 150/26,
        // leaf 1 201/1016, leaf 4 5/66, leaf 5 1/20; leaf 3 is crossed by none.
        let none = [false; 6];
        assert_eq!(shared_leaves(&refs, &crossings, &none, 20), vec![2, 0]);
        // Leaves 1 and 4 do not fit beside leaves 2 and 0; leaf 5, smaller
        // and crossed less, still does.
        assert_eq!(shared_leaves(&refs, &crossings, &none, 25), vec![2, 0, 5]);
        assert_eq!(shared_leaves(&refs, &crossings, &none, 15), vec![2, 5]);
        assert_eq!(shared_leaves(&refs, &crossings, &none, 9), vec![5]);
        assert_eq!(
            shared_leaves(&refs, &crossings, &none, 3),
            Vec::<u32>::new()
        );
        let mut shared = none;
        shared[2] = true;
        assert_eq!(shared_leaves(&refs, &crossings, &shared, 15), vec![0, 5]);
        assert_eq!(
            shared_leaves(&refs, &crossings, &none, 2000),
            vec![2, 0, 1, 4, 5]
        );
    }
}
