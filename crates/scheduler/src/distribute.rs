//! Distribution: each worker gets its job setup (processor map, lights,
//! materials, own leaves, memory plan) and then its region one BVH part at
//! a time, each part's triangles cut from the scene as it is sent, so
//! neither side ever holds a second copy of a whole region. The irradiance
//! cache's known overture levels follow the region.
//!
//! When several workers are shipped the same whole region (a job that
//! replicates the scene) and would each build one BVH over it, the
//! scheduler builds that BVH once, while the parts are on their way, and
//! sends its layout after the last part ([`shared_layout`]): each worker
//! then checks it and gathers its triangles into its order instead of
//! building the same BVH again.

use crate::job::Prepared;
use crate::overture::{Overture, send_levels};
use glam::Vec3;
use locus_core::accel::{BuildQuality, Layout};
use locus_core::scene::Scene;
use locus_protocol::control::{JobSetup, SchedulerToWorker};
use locus_protocol::overture::IrradianceSetup;
use locus_protocol::submit::JobRequest;
use std::sync::Arc;
use std::time::Instant;
use tokio::sync::{mpsc, watch};
use tracing::{info, warn};

/// A layout being built: `None` until it is done, then the layout, or
/// nothing when the build failed (the workers then build their own).
type Pending = watch::Receiver<Option<Option<Arc<Layout>>>>;

/// One worker as the shipment sees it: its listen address, its control
/// channel, and whether it takes layouts (`Registration::layouts`).
pub struct Member {
    pub listen: String,
    pub tx: mpsc::Sender<SchedulerToWorker>,
    pub layouts: bool,
}

/// Starts one task per worker (a slow link does not hold the others)
/// that sends the setup and the parts. `txs[w]` is worker `w`'s listen
/// address and control channel.
pub fn ship(
    id: u64,
    req: &JobRequest,
    prep: &mut Prepared,
    members: Vec<Member>,
    overture: Option<&Overture>,
) {
    let peers: Vec<String> = members.iter().map(|m| m.listen.clone()).collect();
    let takers: Vec<bool> = members.iter().map(|m| m.layouts).collect();
    let layout = shared_layout(id, prep, &takers);
    let mut own_leaves = std::mem::take(&mut prep.own_leaves);
    for (w, Member { tx, .. }) in members.into_iter().enumerate() {
        let own = std::mem::take(&mut own_leaves[w]);
        let layout = layout
            .as_ref()
            .filter(|(ws, _)| ws.contains(&w))
            .map(|(_, p)| p.clone());
        // Each part: its leaves, and their triangles once each.
        let runs = std::mem::take(&mut prep.parts[w]);
        let setup = JobSetup {
            job: id,
            me: w as u16,
            peers: peers.clone(),
            camera: prep.scene.camera.clone(),
            spp: prep.scene.settings.spp,
            max_depth: prep.scene.settings.max_depth,
            seed: prep.scene.settings.seed,
            sampler: prep.scene.settings.sampler,
            materials: prep.scene.materials.clone(),
            lights: prep.lights.clone(),
            map: prep.map_for(w as u16),
            magnitude: prep.scene.magnitude(),
            tuning: locus_protocol::control::Tuning {
                max_inflight: prep.max_inflight[w],
                ..req.options.tuning
            },
            cache: req.options.cache,
            irradiance: overture
                .zip(prep.irradiance.as_ref())
                .map(|(o, p)| IrradianceSetup {
                    params: o.params,
                    bounds: p.bounds,
                    known: o.levels.len() as u32,
                    shares: crate::actor::shares(&prep.member_cores),
                }),
            fetch: req.options.fetch,
            plan: prep.plans[w],
            own_leaves: own,
            leaf_tris: prep.leaf_tris.clone(),
            region_triangles: prep.region_triangles[w],
            normals: !prep.scene.tri_normals.is_empty(),
            layout: layout.is_some(),
            bvh_quality: prep.bvh_quality,
        };
        let scene = prep.scene.clone();
        // The overture's known levels follow the geometry.
        let (known, sent) = overture.map_or((Vec::new(), Default::default()), |o| {
            (o.levels.clone(), o.bytes_sent.clone())
        });
        tokio::spawn(async move {
            tx.send(SchedulerToWorker::StartJob(Box::new(setup)))
                .await?;
            let n = runs.len();
            if n == 0 {
                // A worker without leaves still closes its shipment.
                let last = SchedulerToWorker::Geometry {
                    job: id,
                    leaves: Vec::new(),
                    chunk: Default::default(),
                    last: true,
                };
                tx.send(last).await?;
                return send_levels(&tx, id, 0, &known, &sent).await;
            }
            for (k, run) in runs.into_iter().enumerate() {
                // A part is up to 48 MiB of copying: off the runtime, and
                // once for every worker shipped the same run. A panic there
                // is a bug, and stays one.
                let scene = scene.clone();
                let (leaves, chunk) = tokio::task::spawn_blocking(move || {
                    let chunk = run.gather(&scene);
                    (run.leaves, chunk)
                })
                .await
                .unwrap_or_else(|e| std::panic::resume_unwind(e.into_panic()));
                tx.send(SchedulerToWorker::Geometry {
                    job: id,
                    leaves,
                    chunk,
                    last: k + 1 == n,
                })
                .await?;
            }
            if let Some(mut pending) = layout {
                // The build task sends before it ends; a runtime shutting
                // down drops it unsent, and the worker builds its own.
                let layout = pending
                    .wait_for(Option::is_some)
                    .await
                    .ok()
                    .and_then(|l| l.clone().flatten());
                tx.send(SchedulerToWorker::Layout { job: id, layout })
                    .await?;
            }
            send_levels(&tx, id, 0, &known, &sent).await
        });
    }
}

/// Starts building, off the runtime, the one BVH layout that the workers
/// shipped the same whole region would each build: those that hold the
/// scene replicated, build their region as one BVH (no memory budget) and
/// take layouts. Returns them and the layout to come, or None where fewer
/// than two would share it (one worker builds as fast as the scheduler).
fn shared_layout(job: u64, prep: &Prepared, takers: &[bool]) -> Option<(Vec<usize>, Pending)> {
    if !prep.replicated {
        return None;
    }
    let runs = |w: usize| -> Vec<*const Vec<u32>> {
        prep.parts[w].iter().map(|r| Arc::as_ptr(&r.ids)).collect()
    };
    let eligible = |w: usize| takers[w] && prep.plans[w].budget == 0 && !prep.parts[w].is_empty();
    let first = (0..takers.len()).find(|&w| eligible(w))?;
    // Workers shipped the same parts share their lists (`PartRun`).
    let same: Vec<usize> = (0..takers.len())
        .filter(|&w| eligible(w) && runs(w) == runs(first))
        .collect();
    if same.len() < 2 {
        return None;
    }
    let ids: Vec<Arc<Vec<u32>>> = prep.parts[first].iter().map(|r| r.ids.clone()).collect();
    let scene = prep.scene.clone();
    let quality = prep.bvh_quality;
    let (tx, rx) = watch::channel(None);
    let (workers, spent) = (same.len(), prep.layout_s.clone());
    tokio::task::spawn_blocking(move || {
        let t = Instant::now();
        let built = std::panic::catch_unwind(move || lay_out(&scene, &ids, quality));
        let seconds = t.elapsed().as_secs_f64();
        spent.store(seconds.to_bits(), std::sync::atomic::Ordering::Relaxed);
        let layout = match built {
            Ok(l) => {
                info!(
                    job,
                    workers,
                    nodes = l.nodes(),
                    bytes = l.bytes(),
                    seconds,
                    "region BVH laid out once for the workers that replicate it"
                );
                Some(Arc::new(l))
            }
            Err(_) => {
                warn!(
                    job,
                    "laying out the replicated region's BVH failed; each worker builds its own"
                );
                None
            }
        };
        let _ = tx.send(Some(layout));
    });
    Some((same, rx))
}

/// The layout of the BVH a worker builds over the parts `ids`: over their
/// triangles merged as the worker merges them (ascending ids, each once).
/// The whole scene (what a replicated job ships) is laid out in place; a
/// part of it over a copy of its vertices alone.
fn lay_out(scene: &Scene, ids: &[Arc<Vec<u32>>], quality: BuildQuality) -> Layout {
    let mut all: Vec<u32> = ids.iter().flat_map(|l| l.iter().copied()).collect();
    all.sort_unstable();
    all.dedup();
    let mag = scene.magnitude();
    // Ascending, distinct and each below the count: all of them, in order.
    if all.len() == scene.tris.len() {
        return Layout::build_over(&scene.tris, &all, mag, quality);
    }
    let verts: Vec<[Vec3; 3]> = all.iter().map(|&i| scene.tris[i as usize]).collect();
    Layout::build_over(&verts, &all, mag, quality)
}
