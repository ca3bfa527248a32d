//! The progressive refinement loop: choose the shooter, let every patch
//! receive, keep the energy ledger, and record convergence.
//!
//! The shooter is the patch side with the most unshot power (ties go to
//! the lowest index), each patch receives independently of the others,
//! and the ledger sums the patches' receipts in patch order, so the
//! solution is the same bits whatever thread or worker received a patch.

use super::mesh::Patch;
use super::shoot::{Receipt, Refine, Shooter, Visibility, receive};
use super::{MAX_LEVELS, RadiosityError, RadiosityParams};
use crate::scene::Scene;
use crate::stats::TraceStats;
use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Where the emitted power went, per channel (W): the identity
/// `emitted = absorbed + unshot + escaped` holds to rounding.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Ledger {
    pub emitted: [f64; 3],
    pub absorbed: [f64; 3],
    /// Shot power that no patch received: it left the scene (or was lost
    /// to discretisation, positive or negative, in a closed one).
    pub escaped: [f64; 3],
    pub unshot: [f64; 3],
}

/// The state of a solution between shots.
pub struct Solver {
    pub patches: Vec<Patch>,
    /// Per scene triangle: its first patch and the levels of midpoint
    /// splitting that made its `4^levels` patches.
    first_patch: Vec<(u32, u32)>,
    pub params: RadiosityParams,
    emitted: DVec3,
    absorbed: DVec3,
    escaped: DVec3,
    /// Floor of the subdivision criterion: a thousandth of the brightest
    /// emitted radiosity.
    floor: f32,
    pub elements: u64,
    pub iterations: u64,
    pub stats: TraceStats,
}

/// One measured point of the convergence.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Record {
    pub iteration: u64,
    pub seconds: f64,
    /// Unshot power over emitted power (mean of the channels).
    pub unshot_fraction: f64,
    pub elements: u64,
    pub rays: u64,
    /// Relative L2 difference of the patches' radiosity from the final
    /// solution's (area-weighted); filled in when the solution ends.
    pub error: Option<f64>,
}

/// A patch's two sides' mean radiosity levels (the error series' unit).
pub fn patch_levels(p: &Patch) -> [f32; 2] {
    [0, 1].map(|s| power(p.mean_radiosity(s)) as f32)
}

fn power(c: DVec3) -> f64 {
    (c.x + c.y + c.z) / 3.0
}

impl Solver {
    /// Splits `scene`'s triangles into patches and meshes them.
    pub fn new(scene: &Scene, params: RadiosityParams) -> Result<Self, RadiosityError> {
        params.check()?;
        let extent = crate::geometry::Bounds::of_triangles(&scene.tris)
            .extent()
            .max_element() as f64;
        let levels_for = |t: &[Vec3; 3], divisions: u32, cap: u32| {
            let longest = (0..3)
                .map(|k| (t[(k + 1) % 3] - t[k]).length() as f64)
                .fold(0.0, f64::max);
            (longest / (extent / divisions as f64))
                .log2()
                .ceil()
                .clamp(0.0, cap as f64) as u32
        };
        // Patch levels per triangle, then element levels per patch, counted
        // before anything is allocated.
        let mut plan = Vec::with_capacity(scene.tris.len());
        let mut needed = 0u64;
        for (i, t) in scene.tris.iter().enumerate() {
            let area = crate::geometry::tri_area_f64(t);
            if area.is_nan() || area <= 0.0 {
                return Err(RadiosityError::ZeroArea {
                    scene: scene.path.clone(),
                    triangle: i,
                });
            }
            let lp = levels_for(t, params.patches, 15);
            // Each patch is the triangle shrunk 2^lp times.
            let shrunk = t.map(|v| t[0] + (v - t[0]) / (1u32 << lp) as f32);
            let le = levels_for(&shrunk, params.mesh, MAX_LEVELS - params.subdivide);
            needed = needed.saturating_add(1u64 << (2 * (lp + le).min(31)));
            plan.push((lp, le));
        }
        if needed > params.max_elements {
            return Err(RadiosityError::TooManyElements {
                scene: scene.path.clone(),
                needed,
                limit: params.max_elements,
            });
        }
        let mut patches = Vec::new();
        let mut first_patch = Vec::with_capacity(scene.tris.len());
        let mut emitted = DVec3::ZERO;
        let mut brightest = 0.0f32;
        for (i, t) in scene.tris.iter().enumerate() {
            let m = &scene.materials[scene.tri_material[i] as usize];
            let (lp, le) = plan[i];
            first_patch.push((patches.len() as u32, lp));
            for part in super::formfactor::parts(t, lp) {
                let albedo = m.albedo.clamp(Vec3::ZERO, Vec3::ONE);
                let p = Patch::new(part, albedo, m.emission, le, le + params.subdivide);
                emitted += p.emitted.as_dvec3() * p.area;
                brightest = brightest.max(p.emitted.max_element());
                patches.push(p);
            }
        }
        if power(emitted) <= 0.0 {
            return Err(RadiosityError::NoEmitter {
                scene: scene.path.clone(),
            });
        }
        Ok(Self {
            patches,
            first_patch,
            params,
            emitted,
            absorbed: DVec3::ZERO,
            escaped: DVec3::ZERO,
            floor: brightest * 1e-3,
            elements: needed,
            iterations: 0,
            stats: TraceStats::default(),
        })
    }

    /// The patch holding the point with barycentrics `(b1, b2)` on scene
    /// triangle `tri`, and the point's barycentrics on that patch: the
    /// descent through the midpoint splits that made the patches.
    pub fn locate_patch(&self, tri: u32, b1: f32, b2: f32) -> (u32, f32, f32) {
        let (first, levels) = self.first_patch[tri as usize];
        let mut w = [1.0 - b1 - b2, b1, b2];
        let mut index = 0u32;
        for _ in 0..levels {
            let (child, next) = if w[0] >= 0.5 {
                (0, [2.0 * w[0] - 1.0, 2.0 * w[1], 2.0 * w[2]])
            } else if w[1] >= 0.5 {
                (1, [2.0 * w[0], 2.0 * w[1] - 1.0, 2.0 * w[2]])
            } else if w[2] >= 0.5 {
                (2, [2.0 * w[0], 2.0 * w[1], 2.0 * w[2] - 1.0])
            } else {
                (3, [1.0 - 2.0 * w[0], 1.0 - 2.0 * w[1], 1.0 - 2.0 * w[2]])
            };
            index = index * 4 + child;
            w = next;
        }
        (first + index, w[1], w[2])
    }

    /// The patch side with the most unshot power, and that power.
    pub fn next_shooter(&self) -> Option<(u32, usize, f64)> {
        let mut best: Option<(u32, usize, f64)> = None;
        for (i, p) in self.patches.iter().enumerate() {
            for s in 0..2 {
                let w = p.unshot_power(s);
                if w > 0.0 && best.is_none_or(|b| w > b.2) {
                    best = Some((i as u32, s, w));
                }
            }
        }
        best
    }

    pub fn unshot(&self) -> DVec3 {
        self.patches
            .iter()
            .map(|p| (p.unshot[0] + p.unshot[1]) * p.area)
            .sum()
    }

    pub fn unshot_fraction(&self) -> f64 {
        power(self.unshot()) / power(self.emitted)
    }

    pub fn ledger(&self) -> Ledger {
        Ledger {
            emitted: self.emitted.to_array(),
            absorbed: self.absorbed.to_array(),
            escaped: self.escaped.to_array(),
            unshot: self.unshot().to_array(),
        }
    }

    /// The next shooter, taken off its patch: the farm hands this to every
    /// worker. `None` when nothing is left to shoot.
    pub fn take_shooter(&mut self) -> Option<Shooter> {
        let (i, s, _) = self.next_shooter()?;
        let p = &mut self.patches[i as usize];
        let delta = std::mem::take(&mut p.unshot[s]);
        Some(Shooter::new(i, s, p, delta, self.params.part_levels()))
    }

    /// Subdivision settings for the next shot: the elements still allowed
    /// are shared evenly by the patches, so no shot can pass the limit.
    pub fn refine(&self) -> Refine {
        let left = self.params.max_elements.saturating_sub(self.elements);
        Refine {
            threshold: self.params.threshold,
            floor: self.floor,
            budget: left / self.patches.len().max(1) as u64,
        }
    }

    /// Books one shot's receipts, in patch order.
    pub fn book(&mut self, shooter: &Shooter, receipts: &[Receipt]) {
        let shot = shooter.delta * self.patches[shooter.patch as usize].area;
        let mut received = DVec3::ZERO;
        for (p, r) in self.patches.iter_mut().zip(receipts) {
            let rho = p.albedo.as_dvec3();
            for s in 0..2 {
                received += r.received[s];
                self.absorbed += (DVec3::ONE - rho) * r.received[s];
            }
            p.book(r);
            self.elements += r.new_elements;
        }
        self.escaped += shot - received;
        self.iterations += 1;
    }

    /// One iteration on a pool: shoot, receive everywhere, book. False when
    /// nothing was left to shoot.
    pub fn iterate(&mut self, vis: &dyn Visibility) -> bool {
        use rayon::prelude::*;
        let Some(shooter) = self.take_shooter() else {
            return false;
        };
        let refine = self.refine();
        let out: Vec<(Receipt, TraceStats)> = self
            .patches
            .par_iter_mut()
            .enumerate()
            .map(|(i, p)| {
                let mut st = TraceStats::default();
                let r = receive(p, i as u32, &shooter, vis, refine, &mut st);
                (r, st)
            })
            .collect();
        let receipts: Vec<Receipt> = out.iter().map(|o| o.0).collect();
        for (_, st) in &out {
            self.stats += *st;
        }
        self.book(&shooter, &receipts);
        true
    }

    /// Moves every patch to the worker `owner[patch]` (of `workers`),
    /// leaving its shell here: enough to choose shooters and keep the
    /// ledger while the workers receive.
    pub fn hand_out(&mut self, owner: &[u32], workers: usize) -> Vec<Vec<(u32, Patch)>> {
        assert_eq!(owner.len(), self.patches.len(), "one owner per patch");
        let mut out: Vec<Vec<(u32, Patch)>> = (0..workers).map(|_| Vec::new()).collect();
        for (i, (p, &w)) in self.patches.iter_mut().zip(owner).enumerate() {
            let shell = p.shell();
            out[w as usize].push((i as u32, std::mem::replace(p, shell)));
        }
        out
    }

    /// Puts patches handed out back in place of their shells.
    pub fn take_back(&mut self, patches: Vec<(u32, Patch)>) {
        for (i, p) in patches {
            self.patches[i as usize] = p;
        }
    }

    /// Each patch side's mean radiosity level, for the error series.
    pub fn levels(&self) -> Vec<f32> {
        self.patches.iter().flat_map(patch_levels).collect()
    }

    pub fn vertices(&self) -> u64 {
        self.patches.iter().map(|p| p.vertices.len() as u64).sum()
    }

    pub fn bytes(&self) -> usize {
        self.patches.iter().map(Patch::bytes).sum()
    }
}

/// How a solution converged: a record per iteration at geometrically
/// spaced iterations (about 2% apart), and the last.
pub struct Convergence {
    pub records: Vec<Record>,
    pub seconds: f64,
    /// Why iteration stopped.
    pub stopped: &'static str,
}

/// How iterations are carried out: on this machine ([`LocalShots`]) or by
/// a farm, whose workers hold the patches meanwhile.
pub trait Shots {
    /// One iteration: shoot the next shooter, let every patch receive, and
    /// book it into `solver`. With `snapshot`, each patch side's mean
    /// radiosity after the shot is kept for the error series. False when
    /// nothing was left to shoot (or the shot could not be made).
    fn shoot(&mut self, solver: &mut Solver, snapshot: bool) -> bool;
    /// Ends the iterations: every patch is back in `solver`, and the
    /// snapshots kept, in order.
    fn finish(&mut self, solver: &mut Solver) -> Vec<Vec<f32>>;
}

/// Iterations on this machine's pool, with visibility from `vis`.
pub struct LocalShots<'a> {
    pub vis: &'a dyn Visibility,
    snapshots: Vec<Vec<f32>>,
}

impl<'a> LocalShots<'a> {
    pub fn new(vis: &'a dyn Visibility) -> Self {
        Self {
            vis,
            snapshots: Vec::new(),
        }
    }
}

impl Shots for LocalShots<'_> {
    fn shoot(&mut self, solver: &mut Solver, snapshot: bool) -> bool {
        let shot = solver.iterate(self.vis);
        if shot && snapshot {
            self.snapshots.push(solver.levels());
        }
        shot
    }

    fn finish(&mut self, _: &mut Solver) -> Vec<Vec<f32>> {
        std::mem::take(&mut self.snapshots)
    }
}

/// Iterates `solver` on this machine until its unshot fraction is below
/// `params.stop`, its iteration limit, or nothing is left to shoot.
/// `progress(solver)` is called after each iteration.
pub fn solve(
    solver: &mut Solver,
    vis: &dyn Visibility,
    progress: &mut dyn FnMut(&Solver),
) -> Convergence {
    solve_with(solver, &mut LocalShots::new(vis), progress)
}

/// [`solve`] with iterations made by `shots`.
pub fn solve_with(
    solver: &mut Solver,
    shots: &mut dyn Shots,
    progress: &mut dyn FnMut(&Solver),
) -> Convergence {
    let start = Instant::now();
    let mut records = Vec::new();
    // Snapshots for the error series, at recorded iterations about 1.5x
    // apart, capped in size.
    let mut snapshot_at: Vec<usize> = Vec::new();
    let snapshot_cap = ((64usize << 20) / (8 * solver.patches.len().max(1))).min(64);
    let (mut next_record, mut next_snapshot) = (1u64, 1u64);
    let stopped = loop {
        if solver.unshot_fraction() < solver.params.stop {
            break "converged";
        }
        if solver.iterations >= solver.params.max_iterations {
            break "iteration limit";
        }
        let it = solver.iterations + 1;
        let record_now = it >= next_record;
        let snapshot = record_now && it >= next_snapshot && snapshot_at.len() < snapshot_cap;
        if !shots.shoot(solver, snapshot) {
            break "nothing left to shoot";
        }
        progress(solver);
        if record_now {
            records.push(record(solver, start));
            next_record = (it + 1).max((it as f64 * 1.02).ceil() as u64);
        }
        if snapshot {
            snapshot_at.push(records.len() - 1);
            next_snapshot = (it + 1).max((it as f64 * 1.5).ceil() as u64);
        }
    };
    let snapshots = shots.finish(solver);
    if records
        .last()
        .is_none_or(|r| r.iteration != solver.iterations)
    {
        records.push(record(solver, start));
    }
    fill_errors(solver, &mut records, snapshot_at.into_iter().zip(snapshots));
    Convergence {
        records,
        seconds: start.elapsed().as_secs_f64(),
        stopped,
    }
}

/// Each snapshot's relative L2 difference from the final solution
/// (area-weighted over patch sides), into the record it was taken at.
fn fill_errors(
    solver: &Solver,
    records: &mut [Record],
    snapshots: impl Iterator<Item = (usize, Vec<f32>)>,
) {
    let last = solver.levels();
    let areas: Vec<f64> = solver
        .patches
        .iter()
        .flat_map(|p| [p.area, p.area])
        .collect();
    let norm: f64 = last
        .iter()
        .zip(&areas)
        .map(|(&x, a)| a * (x as f64).powi(2))
        .sum();
    for (at, snap) in snapshots {
        let diff: f64 = snap
            .iter()
            .zip(&last)
            .zip(&areas)
            .map(|((&x, &y), a)| a * (x as f64 - y as f64).powi(2))
            .sum();
        records[at].error = Some(if norm > 0.0 {
            (diff / norm).sqrt()
        } else {
            0.0
        });
    }
    if let Some(r) = records.last_mut() {
        r.error = Some(0.0);
    }
}

fn record(solver: &Solver, start: Instant) -> Record {
    Record {
        iteration: solver.iterations,
        seconds: start.elapsed().as_secs_f64(),
        unshot_fraction: solver.unshot_fraction(),
        elements: solver.elements,
        rays: solver.stats.rays(),
        error: None,
    }
}
