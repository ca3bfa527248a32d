//! Spatial pre-splits: a large, mostly empty triangle box cut into
//! tighter boxes before the BVH build (obvhs's preset, after Embree's
//! pre-splitting), within the growth the memory plans allow for.

use glam::Vec3;
use obvhs::aabb::Aabb;

/// Pre-splits add at most one box per this many triangles. Memory plans
/// size a build by [`super::BUILD_BYTES_PER_TRIANGLE`] and a finished part by the
/// scheduler's bytes per region triangle, both measured without splits and
/// with about 5% to spare.
const MAX_SPLIT_GROWTH: usize = 20;

/// Tight boxes of `verts`, a large triangle's replaced by several boxes of
/// its clipped pieces (obvhs's preset, which splits conservatively enough
/// not to slow traversal on scenes without large triangles), with the
/// triangle each box belongs to. Where the preset would add more boxes
/// than [`MAX_SPLIT_GROWTH`] allows, the largest triangles keep their
/// pieces and the rest their tight box. Pure function of `verts`: the same
/// set builds the same BVH on every worker.
pub(super) fn split_boxes(verts: &[[Vec3; 3]]) -> (Vec<Aabb>, Vec<u32>) {
    let tight: Vec<Aabb> = verts
        .iter()
        .map(|t| Aabb::from_points(&[t[0].into(), t[1].into(), t[2].into()]))
        .collect();
    let n = verts.len();
    let (mut boxes, mut of_box) = (tight.clone(), (0..n as u32).collect::<Vec<u32>>());
    if n < 2 {
        return (boxes, of_box);
    }
    let tris: Vec<obvhs::triangle::Triangle> = verts
        .iter()
        .map(|v| obvhs::triangle::Triangle {
            v0: v[0].into(),
            v1: v[1].into(),
            v2: v[2].into(),
        })
        .collect();
    let (mut largest, mut sum) = (0.0f32, 0.0f64);
    for b in &tight {
        largest = largest.max(b.half_area());
        sum += f64::from(b.half_area());
    }
    let average = (sum / n as f64) as f32;
    obvhs::splits::split_aabbs_preset(&mut boxes, &mut of_box, &tris, average, largest);
    let allowed = n / MAX_SPLIT_GROWTH;
    if boxes.len() - n <= allowed {
        return (boxes, of_box);
    }
    // Each triangle is split on its own (the preset's thresholds are the
    // set's, fixed above), so a triangle's pieces do not depend on which
    // others keep theirs: the largest keep them, within the allowance.
    let mut pieces = vec![0usize; n];
    for &t in &of_box {
        pieces[t as usize] += 1;
    }
    let mut split: Vec<usize> = (0..n).filter(|&t| pieces[t] > 1).collect();
    split.sort_by(|&a, &b| {
        let area = |t: usize| tight[t].half_area();
        area(b).total_cmp(&area(a)).then(a.cmp(&b))
    });
    let mut keep = vec![false; n];
    let mut extra = 0;
    for t in split {
        if extra + pieces[t] - 1 <= allowed {
            keep[t] = true;
            extra += pieces[t] - 1;
        }
    }
    let kept = boxes
        .into_iter()
        .zip(of_box)
        .filter(|&(_, t)| keep[t as usize]);
    let unsplit = (0..n as u32)
        .filter(|&t| !keep[t as usize])
        .map(|t| (tight[t as usize], t));
    unsplit.chain(kept).unzip()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::tests::soup;

    /// A few long triangles are split whole; so many that their pieces
    /// would grow the set by more than a twentieth (what memory plans allow
    /// for) are split largest first within that allowance, and every
    /// triangle keeps at least one box.
    #[test]
    fn pre_splits_stay_within_the_memory_plans_margin() {
        for (small, long) in [(3000, 10), (1000, 400)] {
            let set = soup(small, long);
            let n = set.len();
            let (boxes, of_box) = split_boxes(&set);
            assert_eq!(boxes.len(), of_box.len());
            assert!(boxes.len() > n, "{long} long triangles: nothing split");
            assert!(
                boxes.len() <= n + n / MAX_SPLIT_GROWTH,
                "{} boxes",
                boxes.len()
            );
            let mut seen = vec![0u32; n];
            for (b, &t) in boxes.iter().zip(&of_box) {
                seen[t as usize] += 1;
                // Every piece lies within its triangle's box.
                let v = &set[t as usize];
                let whole = Aabb::from_points(&[v[0].into(), v[1].into(), v[2].into()]);
                assert!(whole.contains_point(b.min) && whole.contains_point(b.max));
            }
            assert!(seen.iter().all(|&k| k >= 1), "a triangle lost its box");
            // The small triangles are never split.
            assert!(seen[..small as usize].iter().all(|&k| k == 1));
        }
    }
}
