//! Setting up one job on a worker: checking what the scheduler sent,
//! building the region's BVH part by part as the parts arrive, linking to
//! every peer, and starting the [`crate::engine`] on its own thread.

use crate::builds::{Origin, SharedBuilds};
use crate::engine::{self, EngineError, EngineJob, Event, Links};
use crate::peers::{self, Inbox, JobLink, OnBreak, Traffic};
use crate::sys;
use anyhow::{Context, bail};
use locus_core::accel::{Accel, BuildQuality, Layout};
use locus_core::accel_set::{self, Part};
use locus_core::irradiance::IrradianceCache;
use locus_protocol::control::{JobSetup, TriangleSet, WorkerToScheduler};
use locus_protocol::handshake::Credentials;
use locus_protocol::overture::LevelChunk;
use locus_protocol::report::WorkerStats;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

/// Capacity of the engine's event channel: enough to keep the engine fed
/// while it traces; a full channel stops the socket readers, which is TCP
/// backpressure on the senders.
const EVENTS: usize = 256;
/// Capacity of each outgoing peer channel, in packets.
const PEER_OUT: usize = 64;

/// A job whose region is arriving.
pub struct Building {
    pub setup: Box<JobSetup>,
    /// The irradiance overture's levels from the scheduler: the sender
    /// goes to the control loop when the region is in.
    pub levels: Option<(flume::Sender<LevelChunk>, flume::Receiver<LevelChunk>)>,
    pub parts: Vec<Arc<Part>>,
    /// Parts received and not built yet: a worker without a memory budget
    /// builds one BVH over its whole region (see [`Building::add_part`]).
    pending: Option<(Vec<u32>, TriangleSet)>,
    pub received: u64,
    pub bvh_s: f64,
    /// Process CPU seconds when the job started (a daemon's own process).
    pub cpu0: f64,
    /// The worker's tracing pool (None for a worker of one thread): idle
    /// while the region arrives, it builds the region's BVHs.
    pub pool: Option<Arc<rayon::ThreadPool>>,
    /// Parts built once for every worker of this process, which then
    /// build on its threads instead (the embedded farm; see
    /// [`crate::builds`]).
    builds: Option<Arc<SharedBuilds>>,
    /// Parts another worker of this process built.
    pub shared_parts: u32,
    /// Parts whose BVH layout the scheduler built and shipped.
    pub shipped_layouts: u32,
    /// Whether the last part has come.
    shipped_all: bool,
}

impl Building {
    /// Checks a job's setup before any geometry is accepted.
    pub fn new(
        setup: Box<JobSetup>,
        dedicated: bool,
        pool: Option<Arc<rayon::ThreadPool>>,
        builds: Option<Arc<SharedBuilds>>,
    ) -> anyhow::Result<Self> {
        check_setup(&setup)?;
        if dedicated {
            // The job's peak is measured from here.
            sys::reset_peak();
        }
        // Unbounded, but the control loop passes on at most the job's
        // `max_records` (see `Starting::pass_level`).
        let levels = setup.irradiance.as_ref().map(|_| flume::unbounded());
        Ok(Self {
            setup,
            levels,
            parts: Vec::new(),
            pending: None,
            received: 0,
            bvh_s: 0.0,
            cpu0: if dedicated { sys::process_cpu_s() } else { 0.0 },
            pool,
            builds,
            shared_parts: 0,
            shipped_layouts: 0,
            shipped_all: false,
        })
    }

    /// Checks one part of the region and builds its BVH off the runtime;
    /// `last` says whether it is the region's last.
    ///
    /// A region ships in parts of a frame each (48 MiB at most), and a
    /// worker with a memory budget builds a BVH per part, as its plan
    /// sizes them. A worker without one keeps the parts until the last and
    /// builds one BVH over them all: every ray then descends one BVH, not
    /// one per part. On the country kitchen (1,443,486 triangles, three
    /// parts) `fetch` on 2 workers rendered at 0.69 of one machine's speed
    /// with three parts a worker.
    /// Returns whether the region is complete: after the last part, or
    /// after the layout that follows it where the setup announced one
    /// ([`Building::add_layout`]).
    pub async fn add_part(
        &mut self,
        leaves: Vec<u32>,
        chunk: TriangleSet,
        last: bool,
    ) -> anyhow::Result<bool> {
        let s = &self.setup;
        if self.shipped_all {
            bail!("a region part after the last");
        }
        if !chunk.is_consistent() {
            bail!("a region part's lists differ in length");
        }
        self.received += chunk.len() as u64;
        if self.received > s.region_triangles {
            bail!(
                "the region holds more than the {} triangles announced",
                s.region_triangles
            );
        }
        if chunk
            .material
            .iter()
            .any(|&m| m as usize >= s.materials.len())
        {
            bail!("region geometry names a material the job does not define");
        }
        if chunk.verts.iter().flatten().any(|p| !p.is_finite()) {
            bail!("region geometry has a non-finite vertex");
        }
        if chunk.normals.iter().flatten().any(|n| !n.is_finite()) {
            bail!("region geometry has a non-finite shading normal");
        }
        if !chunk.ids.is_sorted_by(|a, b| a < b) {
            bail!("a region part's triangle ids are not ascending and distinct");
        }
        if !leaves.is_sorted_by(|a, b| a < b)
            || leaves
                .last()
                .is_some_and(|&l| l as usize >= s.map.owner.len())
        {
            bail!("a region part names leaves that are not ascending or not in the octree");
        }
        let (leaves, chunk) = match self.pending.take() {
            Some((mut held, set)) => {
                if leaves
                    .first()
                    .is_some_and(|&l| held.last().is_some_and(|&h| l <= h))
                {
                    bail!("the region's parts name leaves out of order");
                }
                held.extend(leaves);
                let t = Instant::now();
                let merged = tokio::task::spawn_blocking(move || set.merge(chunk)).await?;
                self.bvh_s += t.elapsed().as_secs_f64();
                (held, merged)
            }
            None => (leaves, chunk),
        };
        self.shipped_all = last;
        // Held for the next part, or for the layout the setup announced.
        if (!last && s.plan.budget == 0) || (last && s.layout) {
            self.pending = Some((leaves, chunk));
            return Ok(false);
        }
        self.build(leaves, chunk, None).await?;
        if last {
            self.join_parts().await?;
        }
        Ok(last)
    }

    /// Joins the region's parts, built one at a time within the memory
    /// budget, into one BVH ([`accel_set::join`]): a ray then makes one
    /// query where it made one for every part it entered. Nothing is
    /// built again; the join holds the parts and the largest of them
    /// once more at its peak.
    ///
    /// A job that fetches leaves (or takes handed ones, random polling)
    /// joins them too: the joined region is never built again
    /// ([`locus_core::accel_set::Part::mergeable`]), and fetched leaves
    /// merge into parts of their own (`reach::merge`), each small enough to
    /// build again within the plan. Kept apart, a region's parts cost each
    /// ray a query for every part it entered: on the 4-million-triangle
    /// room under `adaptive`, 18 to 24 parts a worker took a quarter more
    /// CPU than `forward`'s one joined BVH, with as many forwards.
    async fn join_parts(&mut self) -> anyhow::Result<()> {
        if self.parts.len() < 2 {
            return Ok(());
        }
        let parts = std::mem::take(&mut self.parts);
        let before = parts.len();
        let t = Instant::now();
        self.parts = tokio::task::spawn_blocking(move || {
            let joined = accel_set::join(parts);
            sys::trim_heap();
            joined
        })
        .await?;
        self.bvh_s += t.elapsed().as_secs_f64();
        tracing::debug!(
            job = self.setup.job,
            parts = before,
            joined = self.parts.len(),
            join_s = t.elapsed().as_secs_f64(),
            resident = sys::resident_bytes().unwrap_or(0),
            peak = sys::peak_resident_bytes().unwrap_or(0),
            "region parts joined"
        );
        Ok(())
    }

    /// The scheduler's layout of the whole region, after its last part
    /// ([`JobSetup::layout`]); `None` when the scheduler could not build
    /// it, and this worker builds. Completes the region.
    pub async fn add_layout(&mut self, layout: Option<Arc<Layout>>) -> anyhow::Result<()> {
        if !self.setup.layout || !self.shipped_all {
            bail!("a BVH layout the job did not announce, or before the region's last part");
        }
        let Some((leaves, chunk)) = self.pending.take() else {
            bail!("a second BVH layout for the region");
        };
        self.build(leaves, chunk, layout).await
    }

    /// Builds one BVH part, or takes it from `layout` (checked against the
    /// triangles here) or from another worker of the process.
    async fn build(
        &mut self,
        leaves: Vec<u32>,
        chunk: TriangleSet,
        layout: Option<Arc<Layout>>,
    ) -> anyhow::Result<()> {
        let s = &self.setup;
        let (mag, quality, t) = (s.magnitude, s.bvh_quality, Instant::now());
        let (pool, builds) = (self.pool.clone(), self.builds.clone());
        let (part, origin) = tokio::task::spawn_blocking(move || {
            let built = match (layout, builds) {
                (Some(l), _) => Accel::from_layout(chunk, &l)
                    .map(|a| (Arc::new(Part::new(a, leaves)), Origin::Shipped))
                    .map_err(|e| anyhow::anyhow!("the scheduler's BVH layout: {e}")),
                (None, Some(b)) => Ok(b.part(chunk, leaves, mag, quality)),
                (None, None) => Ok((
                    build_region_part(chunk, leaves, mag, quality, pool.as_deref()),
                    Origin::Built,
                )),
            };
            sys::trim_heap();
            built
        })
        .await??;
        self.bvh_s += t.elapsed().as_secs_f64();
        match origin {
            Origin::Shared => self.shared_parts += 1,
            Origin::Shipped => self.shipped_layouts += 1,
            Origin::Built => {}
        }
        tracing::debug!(
            job = s.job,
            part = self.parts.len(),
            triangles = part.accel.len(),
            bytes = part.accel.bytes(),
            origin = ?origin,
            resident = sys::resident_bytes().unwrap_or(0),
            peak = sys::peak_resident_bytes().unwrap_or(0),
            "region part built"
        );
        self.parts.push(part);
        Ok(())
    }
}

fn check_setup(s: &JobSetup) -> anyhow::Result<()> {
    let n = s.peers.len();
    if s.map.owner.iter().any(|&o| o as usize >= n) || s.me as usize >= n {
        bail!("processor map names a worker outside the job");
    }
    if !s.own_leaves.is_sorted_by(|a, b| a.0 < b.0)
        || s.own_leaves
            .iter()
            .any(|(l, _)| s.map.owner.get(*l as usize) != Some(&s.me))
    {
        bail!("the list of own leaves is not ascending or names a leaf of another worker");
    }
    if s.layout && s.plan.budget != 0 {
        bail!("a BVH layout announced for a region built in parts");
    }
    if s.leaf_tris.len() != s.map.owner.len() {
        bail!("one triangle count per leaf expected");
    }
    if let Some(c) = &s.cache {
        c.check()
            .map_err(|e| anyhow::anyhow!("cache parameters: {e}"))?;
    }
    if let Some(irr) = &s.irradiance {
        irr.check(n)
            .map_err(|e| anyhow::anyhow!("irradiance cache: {e}"))?;
    }
    Ok(())
}

/// One part of the region's BVH, built on the worker's own threads: in its
/// tracing pool, or on this thread alone for a worker of one thread (the
/// BVH builds in parallel wherever a rayon pool has threads).
pub fn build_region_part(
    chunk: TriangleSet,
    leaves: Vec<u32>,
    magnitude: f32,
    quality: BuildQuality,
    pool: Option<&rayon::ThreadPool>,
) -> Arc<Part> {
    let build = move || region_part_now(chunk, leaves, magnitude, quality);
    match pool {
        Some(p) => p.install(build),
        None => {
            let _alone = sys::this_thread_alone();
            build()
        }
    }
}

/// The build itself, out of line so that profiles can set a region's
/// builds apart from rendering on whichever thread they ran
/// (`bench/forward_cost.py`).
#[inline(never)]
fn region_part_now(
    chunk: TriangleSet,
    leaves: Vec<u32>,
    magnitude: f32,
    quality: BuildQuality,
) -> Arc<Part> {
    Arc::new(Part::new(
        Accel::from_set_with(chunk, magnitude, quality),
        leaves,
    ))
}

/// What starting a job needs from the daemon.
pub struct Env {
    pub creds: Arc<Credentials>,
    pub pool: Option<Arc<rayon::ThreadPool>>,
    pub control: flume::Sender<WorkerToScheduler>,
    pub links: Arc<watch::Sender<Option<Arc<JobLink>>>>,
    pub dedicated: bool,
    /// Tracing threads in all, the engine's included.
    pub threads: usize,
    /// The job's cancellation: aborting it while the peers are being
    /// dialed (one may be stopped and never answer) ends the start.
    pub cancel: CancellationToken,
}

/// Links to every peer and starts the engine on the built region.
pub async fn start(b: Building, env: Env) -> anyhow::Result<Arc<JobLink>> {
    let Building {
        setup,
        levels,
        parts,
        bvh_s,
        cpu0,
        received,
        pool: _,
        builds: _,
        shared_parts,
        shipped_layouts,
        shipped_all: _,
        // Built with the last part.
        pending: _,
    } = b;
    if received != setup.region_triangles {
        bail!(
            "the region ended after {received} of the {} triangles announced",
            setup.region_triangles
        );
    }
    let n = setup.peers.len();
    let me = setup.me;
    let job = setup.job;
    info!(
        job,
        me,
        parts = parts.len(),
        triangles = received,
        bvh_s,
        "region built"
    );
    let cancel = env.cancel.clone();
    let traffic = Arc::new(Traffic::new(n));
    let (events_tx, events_rx) = flume::bounded::<Event>(EVENTS);
    let link = Arc::new(JobLink {
        job,
        inbox: Inbox::Engine {
            tx: events_tx.clone(),
            seed: setup.seed,
            sampler: setup.sampler,
            workers: n,
        },
        traffic: traffic.clone(),
        cancel: cancel.clone(),
    });
    // Publish before dialing: peers dial us at the same time.
    env.links.send_replace(Some(link.clone()));

    let (outs, writers) =
        link_peers(&setup.peers, job, me, &env, &traffic, OnBreak::CancelJob).await?;

    let (setup, irradiance) = match (setup.irradiance.is_some(), levels) {
        (true, Some((_, rx))) => {
            let (setup, cache) = irradiance(setup, parts.clone(), rx, &env).await?;
            (setup, Some(cache))
        }
        _ => (setup, None),
    };
    let ej = Arc::new(EngineJob::new(*setup, irradiance));
    let links = Links {
        peers: outs,
        control: env.control.clone(),
        traffic: traffic.clone(),
        cancel: cancel.clone(),
    };
    let (pool, ctl, dedicated) = (env.pool.clone(), env.control.clone(), env.dedicated);
    let setup_cpu = if dedicated {
        sys::process_cpu_s() - cpu0
    } else {
        0.0
    };
    tokio::spawn(async move {
        let res = tokio::task::spawn_blocking(move || {
            engine::run(ej, parts, pool.as_deref(), (events_tx, events_rx), links)
        })
        .await;
        // The engine dropped its senders; a writer's byte count is final
        // once its last write returned.
        for h in writers {
            let _ = tokio::time::timeout(Duration::from_secs(10), h).await;
        }
        let msg = match res {
            Ok(Ok(mut stats)) => {
                stats.bvh_build_s = bvh_s;
                stats.shared_parts = shared_parts;
                stats.shipped_layouts = shipped_layouts;
                if dedicated {
                    stats.cpu_s = sys::process_cpu_s() - cpu0;
                    stats.setup_cpu_s = setup_cpu;
                    stats.peak_rss = sys::peak_resident_bytes().unwrap_or(0);
                }
                add_traffic(&mut stats, &traffic);
                WorkerToScheduler::Report {
                    job,
                    stats: Box::new(stats),
                }
            }
            // Aborted by the scheduler (or the worker shutting down):
            // what was done goes in a report of the aborted run, which
            // the scheduler adds to the job's recovery.
            Ok(Err(EngineError::Cancelled(mut stats))) => {
                add_traffic(&mut stats, &traffic);
                WorkerToScheduler::Report { job, stats }
            }
            Ok(Err(e)) => {
                warn!(job, "job failed: {e}");
                WorkerToScheduler::Failed {
                    job,
                    reason: e.to_string(),
                }
            }
            Err(e) => WorkerToScheduler::Failed {
                job,
                reason: format!("engine crashed: {e}"),
            },
        };
        let _ = ctl.send_async(msg).await;
        cancel.cancel();
    });
    env.control
        .send_async(WorkerToScheduler::Ready { job })
        .await
        .context("scheduler link closed")?;
    Ok(link)
}

/// The job's irradiance cache, from its overture on a blocking thread; the
/// setup goes there and comes back, as it holds the job's geometry.
async fn irradiance(
    setup: Box<JobSetup>,
    parts: Vec<Arc<Part>>,
    levels: flume::Receiver<LevelChunk>,
    env: &Env,
) -> anyhow::Result<(Box<JobSetup>, IrradianceCache)> {
    let (control, cancel, threads) = (env.control.clone(), env.cancel.clone(), env.threads);
    let (setup, built) = tokio::task::spawn_blocking(move || {
        let irr = setup.irradiance.as_ref().expect("checked by the caller");
        let links = crate::overture::Links {
            control: &control,
            levels: &levels,
            cancel: &cancel,
        };
        let built = crate::overture::build(&setup, irr, parts, threads, links);
        (setup, built)
    })
    .await
    .context("the irradiance overture crashed")?;
    let (cache, stats) = built?;
    info!(
        records = stats.records,
        rays = stats.trace.rays(),
        seconds = stats.seconds,
        "irradiance cache built"
    );
    Ok((setup, cache))
}

/// Outgoing peer channels (none for this worker itself) and the tasks
/// writing them.
pub type PeerLinks = (
    Vec<Option<flume::Sender<crate::peers::Outgoing>>>,
    Vec<tokio::task::JoinHandle<()>>,
);

/// Dials every peer of a job (whose links go up as their jobs start: each
/// side publishes its job before dialing), giving up when the job is
/// aborted.
pub async fn link_peers(
    peers: &[String],
    job: u64,
    me: u16,
    env: &Env,
    traffic: &Arc<Traffic>,
    on_break: OnBreak,
) -> anyhow::Result<PeerLinks> {
    let mut outs = Vec::with_capacity(peers.len());
    let mut writers = Vec::with_capacity(peers.len());
    for (w, addr) in peers.iter().enumerate() {
        if w == me as usize {
            outs.push(None);
            continue;
        }
        let (tx, rx) = flume::bounded(PEER_OUT);
        let dial = peers::dial(
            addr,
            &env.creds,
            job,
            me,
            w as u16,
            rx,
            traffic.clone(),
            env.cancel.clone(),
            on_break,
        );
        let h = tokio::select! {
            _ = env.cancel.cancelled() => bail!("the job was aborted while linking to its peers"),
            h = dial => h.with_context(|| format!("linking to peer {w} at {addr}"))?,
        };
        writers.push(h);
        outs.push(Some(tx));
    }
    Ok((outs, writers))
}

fn add_traffic(stats: &mut WorkerStats, t: &Traffic) {
    for (p, c) in stats.peers.iter_mut().zip(t.snapshot()) {
        *p = c;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use locus_core::geometry::FLAT;
    use locus_protocol::control::MemoryPlan;
    use locus_protocol::submit::FetchPolicy;

    /// A one-worker job over `tris`, whose region ships as `shipped`
    /// triangles, with a memory budget of `budget` bytes.
    fn setup(tris: &[[Vec3; 3]], shipped: u64, budget: u64) -> Box<JobSetup> {
        let base = locus_protocol::testing::job_setup(tris, 1);
        Box::new(JobSetup {
            job: 7,
            plan: MemoryPlan {
                budget,
                ..base.plan
            },
            region_triangles: shipped,
            ..base
        })
    }

    /// The triangles `ids` of `tris` as shipped: ascending, material 0.
    fn part(tris: &[[Vec3; 3]], ids: std::ops::Range<u32>) -> TriangleSet {
        let mut s = TriangleSet::with_capacity(ids.len());
        for id in ids {
            s.push(id, tris[id as usize], 0, FLAT);
        }
        s
    }

    /// Without a budget the parts of a region are kept until the last and
    /// built as one BVH, a triangle shipped in two parts held once; with
    /// one, each part is built as it comes, as the plan sized it, and they
    /// are joined into one BVH after the last (`accel_set::join`), under
    /// every policy; a joined region is never built again by a merge (a
    /// fetching job's leaves make parts of their own), one built whole is.
    #[tokio::test]
    async fn a_region_is_one_bvh_however_it_ships_and_whatever_it_fetches() {
        let tris: Vec<[Vec3; 3]> = (0..30)
            .map(|i| {
                let p = Vec3::new(i as f32 * 0.3 - 4.5, (i % 5) as f32, (i % 7) as f32 * 0.5);
                [p, p + Vec3::X, p + Vec3::Y]
            })
            .collect();
        // Three parts over leaves 0, 1 and 2 (as far as the octree has
        // them), triangles 10 to 14 in the first two.
        let part = |ids| part(&tris, ids);
        let shipped = [part(0..15), part(10..20), part(20..30)];
        let n: u64 = shipped.iter().map(|s| s.len() as u64).sum();
        for (budget, fetch) in [
            (0u64, FetchPolicy::Forward),
            (1 << 30, FetchPolicy::Forward),
            (1 << 30, FetchPolicy::Adaptive),
        ] {
            let mut setup = setup(&tris, n, budget);
            setup.fetch = fetch;
            let mut b = Building::new(setup, false, None, None).unwrap();
            for (k, s) in shipped.iter().enumerate() {
                b.add_part(vec![k as u32], s.clone(), k == 2).await.unwrap();
            }
            assert_eq!(b.parts.len(), 1, "budget {budget}, {fetch:?}");
            assert_eq!(b.parts[0].accel.len(), 30);
            assert_eq!(b.parts[0].leaves, vec![0, 1, 2]);
            assert_eq!(b.parts[0].mergeable, budget == 0, "{fetch:?}");
            for id in 0..30 {
                let p = b.parts[0].accel.find(id);
                assert!(p.is_some(), "triangle {id}, budget {budget}");
                assert_eq!(b.parts[0].accel.triangle(p.unwrap()).0, tris[id as usize]);
            }
        }
        // Parts whose leaves go back are refused.
        let mut b = Building::new(setup(&tris, n, 0), false, None, None).unwrap();
        b.add_part(vec![1], shipped[0].clone(), false)
            .await
            .unwrap();
        let e = b.add_part(vec![0], shipped[1].clone(), true).await;
        assert!(e.unwrap_err().to_string().contains("out of order"));
    }

    /// A region whose setup announces a layout is held after its last
    /// part until the layout comes, and is then that layout's BVH over
    /// the merged parts, as large as the worker's own build; `None` (the
    /// scheduler's build failed) and it builds its own. A layout of other
    /// triangles fails with the reason, and one not announced, a second
    /// one, or a part after the last, is refused.
    #[tokio::test]
    async fn an_announced_layout_is_checked_and_taken() {
        let tris: Vec<[Vec3; 3]> = (0..40)
            .map(|i| {
                let p = Vec3::new(i as f32 * 0.2 - 4.0, (i % 3) as f32, (i % 4) as f32 * 0.7);
                [p, p + Vec3::X, p + Vec3::Z]
            })
            .collect();
        let part = |ids| part(&tris, ids);
        let shipped = [part(0..25), part(20..40)];
        let whole = part(0..40);
        let n = 45;
        let mag = setup(&tris, n, 0).magnitude;
        // Built at the quality the job's worker builds at, so that the
        // layout's BVH and the worker's own are the same.
        let quality = setup(&tris, n, 0).bvh_quality;
        let layout = Arc::new(Layout::build(&whole, mag, quality));
        let own = Accel::from_set_with(whole.clone(), mag, quality);
        let announced = |layout| {
            let mut s = setup(&tris, n, 0);
            s.layout = layout;
            Building::new(s, false, None, None).unwrap()
        };
        for given in [Some(layout.clone()), None] {
            let mut b = announced(true);
            assert!(
                !b.add_part(vec![0], shipped[0].clone(), false)
                    .await
                    .unwrap()
            );
            assert!(!b.add_part(vec![1], shipped[1].clone(), true).await.unwrap());
            assert!(b.parts.is_empty(), "built before the layout came");
            let e = b.add_part(vec![2], part(0..1), true).await.unwrap_err();
            assert!(e.to_string().contains("after the last"), "{e}");
            let took = given.is_some();
            b.add_layout(given).await.unwrap();
            assert_eq!(b.parts.len(), 1);
            assert_eq!((b.shipped_layouts, took), (took as u32, took));
            assert!(b.parts[0].accel.holds_exactly(&whole));
            assert_eq!(b.parts[0].accel.bytes(), own.bytes());
            let e = b.add_layout(Some(layout.clone())).await.unwrap_err();
            assert!(e.to_string().contains("second"), "{e}");
        }
        // A layout over other triangles.
        let other = Arc::new(Layout::build(&part(0..39), mag, quality));
        let mut b = announced(true);
        b.add_part(vec![0], whole.clone(), true).await.unwrap();
        let e = b.add_layout(Some(other)).await.unwrap_err();
        assert!(e.to_string().contains("other triangles"), "{e}");
        // A layout the setup did not announce.
        let mut b = announced(false);
        assert!(b.add_part(vec![0], whole.clone(), true).await.unwrap());
        let e = b.add_layout(Some(layout)).await.unwrap_err();
        assert!(e.to_string().contains("did not announce"), "{e}");
    }
}
