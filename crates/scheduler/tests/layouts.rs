//! A replicated region's BVH layout as the scheduler's actor ships it,
//! through its channels (see `common`).

mod common;
use common::*;
use locus_core::accel::{Accel, Layout};
use locus_core::geometry::TriangleSet;
use locus_protocol::control::SchedulerToWorker;
use locus_protocol::submit::FetchPolicy;
use std::sync::Arc;
use tokio::sync::mpsc;

/// A worker's shipment of one job: its parts merged as the worker merges
/// them, whether its setup announced a layout, and the layout if one came
/// after the last part (the next message).
async fn shipment(
    w: &mut mpsc::Receiver<SchedulerToWorker>,
) -> (TriangleSet, bool, Option<Arc<Layout>>) {
    let mut set = TriangleSet::default();
    let mut announced = None;
    loop {
        match recv(w).await {
            SchedulerToWorker::StartJob(s) => announced = Some(s.layout),
            SchedulerToWorker::Geometry { chunk, last, .. } => {
                set = set.merge(Arc::unwrap_or_clone(chunk));
                if last {
                    break;
                }
            }
            SchedulerToWorker::Layout { .. } => panic!("a layout before the last part"),
            _ => {}
        }
    }
    let announced = announced.expect("the setup before the parts");
    if !announced {
        return (set, false, None);
    }
    match recv(w).await {
        SchedulerToWorker::Layout { layout, .. } => (set, true, Some(layout.expect("built"))),
        other => panic!("expected the layout after the last part, got {other:?}"),
    }
}

/// A job that replicates the scene announces, to the workers that take
/// layouts, one layout built once, and sends it after their last part; it
/// fits the triangles they were shipped. A worker that does not take them,
/// and any job that does not replicate, gets none.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicated_regions_come_with_one_layout_for_those_that_take_it() {
    let farm = start();
    let mut ws = Vec::new();
    for (id, takes) in [(1, true), (2, false), (3, true)] {
        ws.push(farm.worker_as(id, 1024, takes).await);
    }
    for fetch in [FetchPolicy::Fetch, FetchPolicy::Forward] {
        let mut req = request(3, 1, None);
        req.options.fetch = fetch;
        let mut client = farm.submit_request(req).await;
        accepted(&mut client).await;
        let mut laid = Vec::new();
        for (k, w) in ws.iter_mut().enumerate() {
            let (set, announced, layout) = shipment(w).await;
            let wanted = fetch == FetchPolicy::Fetch && k != 1;
            assert_eq!(announced, wanted, "{fetch:?}, worker {k}");
            match layout {
                Some(l) if wanted => {
                    assert!(set.len() > 30, "the whole Cornell box");
                    Accel::from_layout(set, &l).expect("a layout of the shipment");
                    laid.push(l);
                }
                None if !wanted => {}
                other => panic!("{fetch:?}, worker {k}: layout {}", other.is_some()),
            }
        }
        if fetch == FetchPolicy::Fetch {
            assert_eq!(laid.len(), 2);
            // One layout, held once by the scheduler: the same allocation
            // in both workers' messages, not a copy each.
            assert!(Arc::ptr_eq(&laid[0], &laid[1]), "one layout for both");
        }
        // The client leaves: the job is aborted and the next one starts.
        drop(client);
    }
    farm.shutdown.cancel();
}
