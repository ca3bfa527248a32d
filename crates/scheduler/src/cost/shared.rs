//! What every worker holds beside its region: the leaves a preview's rays
//! cross most per triangle, or that save the most forwards once there are
//! regions ([`shared_leaves`], [`Preview::share_values`]), and the
//! crossings that are left once those are passed over
//! ([`Preview::crossings_beside`]), along which regions are grown
//! (`job::regions`).

use super::{Crossings, PATH_END, Preview, SHADOW_END, WALK_END};
use locus_core::region::WorkerId;

impl Preview {
    /// The crossings a farm forwards once the `shared` leaves (which every
    /// worker holds, so that no query is forwarded into them) are passed
    /// over like the camera's. A path is held, ray after ray, by whoever
    /// holds the last leaf it entered that is not shared (the worker that
    /// shades a vertex traces its continuation), so its run of such leaves
    /// goes on across its rays: a path from leaf `a` through shared leaves,
    /// or off a shared surface and on, into leaf `b` crosses from `a` into
    /// `b`. A shadow ray branches off its path and leaves it where it was.
    /// Until a path enters a leaf that is not shared, its first such leaf
    /// holds it: its tile goes to that leaf's owner
    /// ([`Preview::first_leaves`]), so entering it is no crossing, and a
    /// shadow ray from a shared surface before it into another leaf is.
    pub fn crossings_beside(&self, shared: &[bool]) -> Crossings {
        self.crossings_beside_from(shared, &self.first_leaves(shared))
    }

    /// [`Preview::crossings_beside`] with the paths' first leaves beside
    /// the `shared` ones already known ([`Preview::first_leaves`]).
    pub fn crossings_beside_from(&self, shared: &[bool], first: &[Option<u32>]) -> Crossings {
        let mut out = Crossings::default();
        self.follow(shared, first, |e| {
            if let Some(p) = e.held.filter(|&p| !e.shared && p != e.leaf) {
                *out.entry((p, e.leaf)).or_default() += 1;
            }
        });
        out
    }

    /// Per path (in the order of [`Preview::pixels`]), the first leaf
    /// beside the `shared` ones that its rays enter (its shadow rays
    /// aside): whoever owns it holds the path from there, so the tile
    /// whose paths mostly enter one worker's leaves first is best started
    /// by that worker (`tiles::affinities`). None for a path that meets
    /// shared leaves only.
    pub fn first_leaves(&self, shared: &[bool]) -> Vec<Option<u32>> {
        let mut first = vec![None; self.pixels.len()];
        self.follow(shared, &[], |e| {
            if !e.shadow
                && !e.shared
                && let Some(f) = first.get_mut(e.path)
            {
                f.get_or_insert(e.leaf);
            }
        });
        first
    }

    /// Each path's pixel beside its first leaf (`first`, from
    /// [`Preview::first_leaves`]): what tiles vote by (`tiles::votes`,
    /// `tiles::affinities`).
    pub fn pixel_firsts(&self, first: &[Option<u32>]) -> Vec<((u32, u32), Option<u32>)> {
        self.pixels
            .iter()
            .copied()
            .zip(first.iter().copied())
            .collect()
    }

    /// The queries the farm forwards for the preview's paths, predicted:
    /// each path started by the worker `starts` names (its tile's; where
    /// none, the owner of its first leaf), then held by the owner of the
    /// last leaf beside the `shared` ones it entered, a shadow ray
    /// branching off; a ray entering a leaf of another worker than the
    /// holder's is one forward. Against [`Preview::crossings_beside`] this
    /// counts a path whose tile went elsewhere than its first leaf: the
    /// tile's owner forwards it there (a tile has one owner for paths that
    /// scatter).
    pub fn forwards_from(
        &self,
        shared: &[bool],
        owner: &[WorkerId],
        starts: &[Option<WorkerId>],
    ) -> u64 {
        let own = |l: u32| owner.get(l as usize).copied();
        let mut n = 0;
        self.follow(shared, &[], |e| {
            let start = || starts.get(e.path).copied().flatten();
            let from = e.held.map_or_else(start, own);
            if !e.shared && from.is_some_and(|w| Some(w) != own(e.leaf)) {
                n += 1;
            }
        });
        n
    }

    /// Per leaf, the forwards that sharing it would save (or, for a
    /// shared one, that unsharing it would add) with the other leaves'
    /// sharing and the `owner`s as they are, each path started by the
    /// worker `starts` names. A ray that enters leaf `l` of another worker
    /// than its holder `h` is forwarded there, and its path or ray then
    /// goes on with `l`'s owner; with `l` shared it stays with `h`. So the
    /// entry saves its own forward, and at the next leaf `m` beside `l`
    /// and the shared ones that the path enters, a forward where `m`'s
    /// owner is not `l`'s and costs one where it is not `h`. A shadow ray
    /// off the path before `m` settles the same at its own first such
    /// leaf, without the entry's own forward.
    pub fn share_values(
        &self,
        shared: &[bool],
        owner: &[WorkerId],
        starts: &[Option<WorkerId>],
    ) -> Vec<i64> {
        let own = |l: u32| owner.get(l as usize).copied();
        let mut worth = Worth {
            value: vec![0; owner.len()],
            owner,
            on_path: Vec::new(),
            on_ray: Vec::new(),
        };
        let (mut path, mut last_at) = (usize::MAX, usize::MAX);
        self.follow(shared, &[], |e| {
            if e.path != path {
                worth.end_path();
                path = e.path;
            }
            // A ray's entries are consecutive in the walks.
            if e.at != last_at.wrapping_add(1) {
                worth.end_ray();
            }
            last_at = e.at;
            let holder = e
                .held
                .map_or_else(|| starts.get(e.path).copied().flatten(), own);
            if let Some(h) = holder {
                worth.enter(&e, h);
            }
        });
        worth.end_path();
        worth.value
    }

    /// The leaf costs the partition balances once the `shared` leaves are
    /// every worker's: the work a path does in a shared leaf is charged to
    /// the leaf that holds it there ([`Preview::crossings_beside`]: before
    /// it enters one, its first leaf, whose owner starts it). That is the
    /// worker that does it, where the shared leaves' own costs would say
    /// no one does. The work of a path that meets shared leaves only is
    /// left out: whichever worker starts its tile does it.
    pub fn charged(&self, shared: &[bool]) -> Vec<f64> {
        self.charged_from(shared, &self.first_leaves(shared))
    }

    /// [`Preview::charged`] with the paths' first leaves beside the
    /// `shared` ones already known ([`Preview::first_leaves`]).
    pub fn charged_from(&self, shared: &[bool], first: &[Option<u32>]) -> Vec<f64> {
        let mut cost: Vec<f64> = self
            .cost
            .iter()
            .zip(shared.iter().chain(std::iter::repeat(&false)))
            .map(|(&c, &s)| if s { 0.0 } else { c })
            .collect();
        self.follow(shared, first, |e| {
            if let Some(to) = e.held.filter(|_| e.shared) {
                cost[to as usize] += self.walk_costs.get(e.at).copied().unwrap_or(0) as f64;
            }
        });
        cost
    }

    /// Follows every path's rays through [`Preview::walks`], calling `f`
    /// with each leaf a ray enters ([`Entered`]), ray by ray. Until a path
    /// enters a leaf beside the `shared` ones, the leaf holding it is its
    /// entry in `first` (none where `first` has none).
    fn follow(&self, shared: &[bool], first: &[Option<u32>], mut f: impl FnMut(Entered)) {
        // A ray's entries (index, leaf, the leaf holding the path before),
        // until its end marker says what kind of ray it was.
        let mut run: Vec<(usize, u32, Option<u32>)> = Vec::new();
        let start = |path: usize| first.get(path).copied().flatten();
        let (mut path, mut held, mut before) = (0usize, start(0), start(0));
        for (at, &l) in self.walks.iter().enumerate() {
            match l {
                WALK_END | SHADOW_END => {
                    let shadow = l == SHADOW_END;
                    for &(at, leaf, h) in &run {
                        let shared = shared.get(leaf as usize).copied().unwrap_or(false);
                        f(Entered {
                            path,
                            held: h,
                            leaf,
                            at,
                            shadow,
                            shared,
                        });
                    }
                    run.clear();
                    // A shadow ray leaves the path with the leaf it had.
                    if shadow {
                        held = before;
                    } else {
                        before = held;
                    }
                }
                PATH_END => {
                    path += 1;
                    (held, before) = (start(path), start(path));
                    run.clear();
                }
                _ => {
                    run.push((at, l, held));
                    if !shared.get(l as usize).copied().unwrap_or(false) {
                        held = Some(l);
                    }
                }
            }
        }
    }
}

/// [`Preview::share_values`] as it follows the walks: each leaf's worth
/// so far, and the entries waiting for the next leaf that settles them.
struct Worth<'a> {
    value: Vec<i64>,
    owner: &'a [WorkerId],
    /// Entries into a leaf of another worker than the path's holder:
    /// (leaf, holder, whether the current shadow ray has settled it).
    on_path: Vec<(u32, WorkerId, bool)>,
    /// The same for the current shadow ray: (leaf, holder).
    on_ray: Vec<(u32, WorkerId)>,
}

impl Worth<'_> {
    fn own(&self, l: u32) -> Option<WorkerId> {
        self.owner.get(l as usize).copied()
    }

    fn add(&mut self, l: u32, d: i64) {
        if let Some(v) = self.value.get_mut(l as usize) {
            *v += d;
        }
    }

    /// What an entry into `l` with holder `h` saves at the next leaf,
    /// owned by `x`: a forward there where `x` is not `l`'s owner, less
    /// one where `x` is not `h`.
    fn settle(&self, l: u32, h: WorkerId, x: Option<WorkerId>) -> i64 {
        i64::from(x != self.own(l)) - i64::from(x != Some(h))
    }

    /// A path (or a shadow ray) that ends leaves nothing more to settle:
    /// its entries save their own forwards.
    fn end_path(&mut self) {
        self.end_ray();
        for (l, _, _) in std::mem::take(&mut self.on_path) {
            self.add(l, 1);
        }
    }

    fn end_ray(&mut self) {
        for (l, _) in std::mem::take(&mut self.on_ray) {
            self.add(l, 1);
        }
        self.on_path.iter_mut().for_each(|p| p.2 = false);
    }

    /// A ray held by worker `h` enters `e.leaf`.
    fn enter(&mut self, e: &Entered, h: WorkerId) {
        if !e.shared {
            let x = self.own(e.leaf);
            if e.shadow {
                for (l, hh) in std::mem::take(&mut self.on_ray) {
                    if l == e.leaf {
                        self.on_ray.push((l, hh));
                    } else {
                        self.add(l, 1 + self.settle(l, hh, x));
                    }
                }
                // A shadow ray off a path settles the path's entries at
                // its own first leaf beside them, without their forwards.
                for i in 0..self.on_path.len() {
                    let (l, hh, done) = self.on_path[i];
                    if !done && l != e.leaf {
                        self.add(l, self.settle(l, hh, x));
                        self.on_path[i].2 = true;
                    }
                }
            } else {
                for (l, hh, done) in std::mem::take(&mut self.on_path) {
                    if l == e.leaf {
                        self.on_path.push((l, hh, done));
                    } else {
                        self.add(l, 1 + self.settle(l, hh, x));
                    }
                }
            }
        }
        // A shadow ray into a leaf its path waits in would find that
        // leaf's owner holding it either way: the path's entry counts.
        let waiting = |l: u32, v: &[(u32, WorkerId, bool)]| v.iter().any(|p| p.0 == l);
        if Some(h) == self.own(e.leaf) || waiting(e.leaf, &self.on_path) {
            return;
        }
        if !e.shadow {
            self.on_path.push((e.leaf, h, false));
        } else if !self.on_ray.iter().any(|p| p.0 == e.leaf) {
            self.on_ray.push((e.leaf, h));
        }
    }
}

/// A leaf a preview ray entered, as [`Preview::follow`] sees it.
struct Entered {
    /// The path's index, in the order of [`Preview::pixels`].
    path: usize,
    /// The last leaf beside the shared ones that the path entered before
    /// (before its first, that one where the caller gave it, else None):
    /// whoever holds it holds the path.
    held: Option<u32>,
    leaf: u32,
    /// Its index in [`Preview::walks`].
    at: usize,
    shadow: bool,
    /// Whether `leaf` is one of the shared ones.
    shared: bool,
}

/// Crossings into or out of each of `n` leaves.
pub fn traffic(crossings: &Crossings, n: usize) -> Vec<u64> {
    let mut t = vec![0u64; n];
    for (&(a, b), &c) in crossings {
        t[a as usize] += c as u64;
        t[b as usize] += c as u64;
    }
    t
}

/// Leaves worth giving every worker beside its region (beside those
/// `shared` already), holding at most `most` triangle references in all:
/// those with the most `traffic` per triangle they hold (the preview's
/// crossings into or out of each, [`traffic`], before there are regions;
/// the forwards sharing each would save, [`Preview::share_values`], once
/// there are). Paper 000's hybrid scheduling in the partition's terms: a
/// ray is never forwarded into a leaf every worker holds, so the few
/// triangles that most rays meet (walls, floors, a room's large surfaces)
/// are traced by whoever holds the ray, demand-driven, and only the
/// detailed rest is data-parallel. On the room with 2 workers, a
/// tenth of the triangles shared cut forwarded queries from 0.275 to
/// 0.066 a ray, on the conference room from 0.251 to 0.039 (the README's
/// "Shared leaves").
pub fn shared_leaves(refs: &[u64], traffic: &[u64], shared: &[bool], most: u64) -> Vec<u32> {
    let traffic = |l: usize| traffic.get(l).copied().unwrap_or(0);
    let mut order: Vec<u32> = (0..refs.len() as u32)
        .filter(|&l| !shared[l as usize] && traffic(l as usize) > 0)
        .collect();
    // Per triangle, with a few more counted than a leaf holds, so that a
    // leaf of one or two triangles that a handful of rays cross does not
    // outrank a wall every path meets.
    let score = |l: u32| traffic(l as usize) as f64 / (refs[l as usize] + 16) as f64;
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

    /// A path's run of leaves goes on across its rays, past the shared
    /// leaves it bounces off; a shadow ray branches off it; a path's first
    /// leaf is not a crossing, and nothing carries over from one path to
    /// the next. Leaves: 0 shared, 1, 2 and 3 not.
    #[test]
    fn paths_are_followed_across_their_rays_and_past_shared_leaves() {
        let (s, a, b, c) = (0, 1, 2, 3);
        // Path 0: the camera ray enters a, its shadow ray crosses into b;
        // the bounce from a hits the shared leaf, whose shadow ray (the
        // path still a's) reaches c; the next bounce enters b.
        let path0 = [
            s, a, WALK_END, a, b, SHADOW_END, a, s, WALK_END, s, c, SHADOW_END, s, b, WALK_END,
            PATH_END,
        ];
        // Path 1: shared leaves only, but for its shadow ray into c, which
        // crosses a shared leaf again beyond it.
        let path1 = [s, WALK_END, s, c, s, SHADOW_END, s, WALK_END, PATH_END];
        // Path 2: starts in c and stays there.
        let path2 = [c, WALK_END, PATH_END];
        // Path 3: the camera ray hits the shared leaf, whose shadow ray
        // enters b before the first bounce enters c, its first leaf: c
        // holds it from the start, so the shadow ray crosses from c.
        let path3 = [s, WALK_END, s, b, SHADOW_END, s, c, WALK_END, PATH_END];
        let walks = [&path0[..], &path1, &path2, &path3].concat();
        // Each entry's work: distinct bits on path 0, so that a sum shows
        // which entries were charged.
        let costs0 = [1, 2, 0, 4, 8, 0, 16, 32, 0, 64, 128, 0, 256, 512, 0, 0];
        let costs1 = [1000, 0, 1000, 0, 700, 0, 1000, 0, 0];
        let pv = Preview {
            cost: vec![5000.0, 10.0, 20.0, 30.0],
            rays: 13,
            steps: 0,
            paths: 4,
            crossings: Crossings::default(),
            walks,
            walk_costs: [&costs0[..], &costs1, &[0; 3], &[0; 9]].concat(),
            pixels: vec![(0, 0), (1, 0), (2, 0), (3, 0)],
        };
        let shared = [true, false, false, false];
        let beside = pv.crossings_beside(&shared);
        assert_eq!(
            beside,
            [((a, b), 2), ((a, c), 1), ((c, b), 1)]
                .into_iter()
                .collect::<Crossings>()
        );
        let first = [Some(a), None, Some(c), Some(c)];
        assert_eq!(pv.first_leaves(&shared), first);
        // With nothing shared every change of leaf is a crossing, ray
        // after ray.
        let all = pv.crossings_beside(&[]);
        let want: Crossings = [
            ((s, a), 1),
            ((a, b), 1),
            ((a, s), 1),
            ((s, c), 3),
            ((c, s), 1),
            ((s, b), 2),
        ]
        .into_iter()
        .collect();
        assert_eq!(all, want);
        let first = [Some(s), Some(s), Some(c), Some(s)];
        assert_eq!(pv.first_leaves(&[]), first);
        // Path 0's work in the shared leaf goes to a, which holds it there
        // (its camera ray's, before it entered a, to a as its first leaf;
        // its last bounce's too, the shadow ray into c having left it
        // with a). Path 1's goes to c only where its shadow ray held it;
        // the rest of its work, with no leaf to hold it, to no one.
        assert_eq!(
            pv.charged(&shared),
            [0.0, 10.0 + 1.0 + 32.0 + 64.0 + 256.0, 20.0, 30.0 + 700.0]
        );
        assert_eq!(pv.charged(&[]), pv.cost);
        // Worker by worker (a on worker 0, b and c on 1): path 0 started on
        // worker 1 forwards its camera ray into a, then its shadow ray
        // into b, the next into c and its last bounce into b; path 1's
        // shadow ray into c is forwarded only when a worker started it;
        // path 3 started on worker 0 forwards its shadow ray into b and
        // its bounce into c.
        let owner = [0, 0, 1, 1];
        let starts = [Some(1), None, Some(1), Some(0)];
        assert_eq!(pv.forwards_from(&shared, &owner, &starts), 4 + 2);
        let on_0 = [Some(0); 4];
        assert_eq!(pv.forwards_from(&shared, &owner, &on_0), 3 + 1 + 1 + 2);
    }

    /// On a real preview: with nothing shared the walks give the
    /// preview's crossings; with the most crossed leaf shared, none into
    /// or out of it, every other crossing kept, and some through it
    /// joined up.
    #[test]
    fn crossings_beside_shared_leaves_join_what_went_through_them() {
        let Cornell { tree, pv, .. } = cornell_preview(8, 4);
        let n = tree.leaves.len();
        assert_eq!(pv.crossings_beside(&vec![false; n]), pv.crossings);
        assert_eq!(pv.first_leaves(&[]).len() as u64, pv.paths);
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
        // The shared leaf's own cost is gone, and part of it (the work of
        // paths that held a leaf beside it) is charged to other leaves.
        let all: f64 = pv.cost.iter().sum();
        let own = pv.cost[s as usize];
        let charged: f64 = pv.charged(&shared).iter().sum();
        let moved = charged - (all - own);
        assert!(
            moved > 0.0 && moved <= own,
            "{moved} of leaf {s}'s {own} charged elsewhere"
        );
        assert_eq!(pv.charged(&vec![false; n]), pv.cost);
        // Each path started by its first leaf's owner forwards what the
        // crossings between two workers' leaves count.
        let owner: Vec<WorkerId> = (0..n).map(|l| (l % 3) as WorkerId).collect();
        let starts: Vec<Option<WorkerId>> = pv
            .first_leaves(&shared)
            .iter()
            .map(|f| f.map(|l| owner[l as usize]))
            .collect();
        let forwards = pv.forwards_from(&shared, &owner, &starts);
        assert!(forwards > 0);
        assert_eq!(forwards, crate::cost::cut(&beside, &owner));
        // Started by one worker, whatever their first leaves, they forward
        // more.
        let one = vec![Some(0); starts.len()];
        assert!(pv.forwards_from(&shared, &owner, &one) > forwards);
    }

    /// A leaf's worth in sharing is what toggling it alone does to the
    /// forwards predicted, leaf by leaf on a real preview (brute force:
    /// [`Preview::forwards_from`] with the leaf shared or not), for
    /// several sets of shared leaves, owners and tile starts.
    #[test]
    fn share_values_are_what_toggling_one_leaf_saves() {
        let Cornell { tree, pv, .. } = cornell_preview(8, 4);
        let n = tree.leaves.len();
        let through = traffic(&pv.crossings, n);
        let mut busiest: Vec<usize> = (0..n).collect();
        busiest.sort_by_key(|&l| std::cmp::Reverse(through[l]));
        let mut checked = 0;
        for (workers, shared_count, start) in [(2, 0, None), (3, 2, Some(1)), (4, 5, None)] {
            let owner: Vec<WorkerId> = (0..n)
                .map(|l| ((l * 7 / 3) % workers) as WorkerId)
                .collect();
            let mut shared = vec![false; n];
            for &l in &busiest[..shared_count] {
                shared[l] = true;
            }
            // Each path started by the given worker, or by the owner of
            // its pixel's column's leaf, some worker either way.
            let starts: Vec<Option<WorkerId>> = pv
                .pixels
                .iter()
                .map(|&(x, _)| Some(start.unwrap_or((x as usize % workers) as WorkerId)))
                .collect();
            let values = pv.share_values(&shared, &owner, &starts);
            let base = pv.forwards_from(&shared, &owner, &starts) as i64;
            for l in 0..n {
                let mut toggled = shared.clone();
                toggled[l] = !toggled[l];
                let after = pv.forwards_from(&toggled, &owner, &starts) as i64;
                let saved = if shared[l] {
                    after - base
                } else {
                    base - after
                };
                assert_eq!(values[l], saved, "leaf {l} of {n}, {workers} workers");
                checked += u64::from(saved != 0);
            }
        }
        assert!(checked > 10, "only {checked} leaves whose sharing matters");
    }

    /// Leaves are shared by crossings per triangle, best first, as many
    /// as fit in `most` references; none already shared is picked again.
    #[test]
    fn shared_leaves_are_the_most_crossed_per_triangle_that_fit() {
        let refs = [10, 1000, 10, 0, 50, 4];
        let crossings: Crossings = [
            ((0, 1), 100),
            ((1, 2), 100),
            ((2, 4), 5),
            ((0, 2), 50),
            ((5, 1), 1),
        ]
        .into_iter()
        .collect();
        // Crossings per (triangle + 16): leaf 2 155/26, leaf 0 150/26,
        // leaf 1 201/1016, leaf 4 5/66, leaf 5 1/20; leaf 3 is crossed by none.
        let none = [false; 6];
        let crossings = traffic(&crossings, 6);
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
