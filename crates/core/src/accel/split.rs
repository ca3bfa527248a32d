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

/// obvhs's preset never considers a box whose half area is below three
/// times the set's average; candidates are taken from a little below that
/// (twice), a superset, so the preset decides alone which are split.
const CANDIDATE_AREA: f32 = 2.0;

/// A triangle's tight box.
fn tight(v: &[Vec3; 3]) -> Aabb {
    Aabb::from_points(&[v[0].into(), v[1].into(), v[2].into()])
}

/// Each triangle's tight box, none split, in [`split_boxes`]'s form.
pub(super) fn unsplit_boxes(verts: &[[Vec3; 3]]) -> (Vec<Aabb>, Vec<u32>) {
    (
        verts.iter().map(tight).collect(),
        (0..verts.len() as u32).collect(),
    )
}

/// Tight boxes of `verts`, a large triangle's replaced by several boxes of
/// its clipped pieces (obvhs's preset, which splits conservatively enough
/// not to slow traversal on scenes without large triangles), with the
/// triangle each box belongs to. Where the preset would add more boxes
/// than [`MAX_SPLIT_GROWTH`] allows, the largest triangles keep their
/// pieces and the rest their tight box. Pure function of `verts`: the same
/// set builds the same BVH on every worker.
///
/// Only the candidates (boxes of at least [`CANDIDATE_AREA`] times the
/// average half area) go to the preset, with their triangles: its
/// thresholds are the whole set's, fixed here, and it splits each box on
/// its own, so the pieces are those it would cut from the whole set. A
/// split triangle's first piece takes its box's place and the others are
/// appended, so beside the result the split holds memory for the
/// candidates alone (a copy of every box and triangle held 116 bytes a
/// triangle during the build's preparation).
pub(super) fn split_boxes(verts: &[[Vec3; 3]]) -> (Vec<Aabb>, Vec<u32>) {
    let n = verts.len();
    let mut boxes: Vec<Aabb> = verts.iter().map(tight).collect();
    let mut of_box: Vec<u32> = (0..n as u32).collect();
    if n < 2 {
        return (boxes, of_box);
    }
    let (mut largest, mut sum) = (0.0f32, 0.0f64);
    for b in &boxes {
        largest = largest.max(b.half_area());
        sum += f64::from(b.half_area());
    }
    let average = (sum / n as f64) as f32;
    let candidates: Vec<u32> = (0..n as u32)
        .filter(|&t| boxes[t as usize].half_area() >= CANDIDATE_AREA * average)
        .collect();
    if candidates.is_empty() {
        return (boxes, of_box);
    }
    let tris: Vec<obvhs::triangle::Triangle> = candidates
        .iter()
        .map(|&t| {
            let v = &verts[t as usize];
            obvhs::triangle::Triangle {
                v0: v[0].into(),
                v1: v[1].into(),
                v2: v[2].into(),
            }
        })
        .collect();
    let mut pieces: Vec<Aabb> = candidates.iter().map(|&t| boxes[t as usize]).collect();
    let mut of_piece: Vec<u32> = (0..candidates.len() as u32).collect();
    obvhs::splits::split_aabbs_preset(&mut pieces, &mut of_piece, &tris, average, largest);
    drop(tris);
    // Pieces per candidate; which split candidates keep their pieces:
    // all of them within the allowance, else the largest first.
    let mut count = vec![0usize; candidates.len()];
    for &c in &of_piece {
        count[c as usize] += 1;
    }
    let mut split: Vec<usize> = (0..candidates.len()).filter(|&c| count[c] > 1).collect();
    split.sort_by(|&a, &b| {
        let area = |c: usize| boxes[candidates[c] as usize].half_area();
        area(b).total_cmp(&area(a)).then(a.cmp(&b))
    });
    let (allowed, mut extra) = (n / MAX_SPLIT_GROWTH, 0);
    let mut keep = vec![false; candidates.len()];
    for c in split {
        if extra + count[c] - 1 <= allowed {
            keep[c] = true;
            extra += count[c] - 1;
        }
    }
    let mut placed = vec![false; candidates.len()];
    boxes.reserve(extra);
    of_box.reserve(extra);
    for (b, c) in pieces.into_iter().zip(of_piece) {
        let (c, t) = (c as usize, candidates[c as usize]);
        if !keep[c] {
            continue;
        }
        if placed[c] {
            boxes.push(b);
            of_box.push(t);
        } else {
            boxes[t as usize] = b;
            placed[c] = true;
        }
    }
    (boxes, of_box)
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
