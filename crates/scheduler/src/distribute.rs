//! Distribution: each worker gets its job setup (processor map, lights,
//! materials, own leaves, memory plan) and then its region one BVH part at
//! a time, each part's triangles cut from the scene as it is sent, so
//! neither side ever holds a second copy of a whole region. The irradiance
//! cache's known overture levels follow the region.

use crate::job::{PartRun, Prepared};
use crate::overture::{Overture, send_levels};
use locus_protocol::control::{JobSetup, SchedulerToWorker, TriangleSet};
use locus_protocol::overture::IrradianceSetup;
use locus_protocol::submit::JobRequest;
use std::sync::Arc;
use tokio::sync::mpsc;

/// Starts one task per worker (a slow link does not hold the others)
/// that sends the setup and the parts. `txs[w]` is worker `w`'s listen
/// address and control channel.
pub fn ship(
    id: u64,
    req: &JobRequest,
    prep: &mut Prepared,
    txs: Vec<(String, mpsc::Sender<SchedulerToWorker>)>,
    overture: Option<&Overture>,
) {
    let peers: Vec<String> = txs.iter().map(|(a, _)| a.clone()).collect();
    let mut own_leaves = std::mem::take(&mut prep.own_leaves);
    for (w, (_, tx)) in txs.into_iter().enumerate() {
        let own = std::mem::take(&mut own_leaves[w]);
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
                    chunk: TriangleSet::default(),
                    last: true,
                };
                tx.send(last).await?;
                return send_levels(&tx, id, 0, &known, &sent).await;
            }
            for (k, PartRun { leaves, ids }) in runs.into_iter().enumerate() {
                // A part is up to 48 MiB of copying: off the runtime. A
                // panic there is a bug, and stays one.
                let scene = scene.clone();
                let chunk = tokio::task::spawn_blocking(move || {
                    let ids = Arc::unwrap_or_clone(ids);
                    TriangleSet::gather(ids, &scene.tris, &scene.tri_material, &scene.tri_normals)
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
            send_levels(&tx, id, 0, &known, &sent).await
        });
    }
}
