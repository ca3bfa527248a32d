//! The irradiance cache's overture on a worker, before it renders: the
//! core's [`overture::run`] (the very levels one machine runs) with this
//! worker as one member. It measures its share of each level not known
//! yet on the whole scene it holds, sends it to the scheduler, and adds
//! the level as the scheduler merged it; known levels are only received
//! (`locus_protocol::overture`).

use anyhow::{Context, bail};
use locus_core::accel_set::{AccelSet, Part};
use locus_core::irradiance::IrradianceCache;
use locus_core::irradiance::overture::{self, Measured, OvertureStats, Share};
use locus_core::path::{Kernel, WholeScene};
use locus_core::stats::TraceStats;
use locus_protocol::control::{JobSetup, WorkerToScheduler};
use locus_protocol::overture::{IrradianceSetup, LevelChunk, MeasuredChunk, chunks};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio_util::sync::CancellationToken;

/// How often a wait for the scheduler's level looks at the job's
/// cancellation: the wait ends when the level comes or the job is
/// aborted (the scheduler aborts an attempt that lost a member).
const POLL: Duration = Duration::from_millis(200);

/// Where the overture's messages go and come from.
pub struct Links<'a> {
    pub control: &'a flume::Sender<WorkerToScheduler>,
    pub levels: &'a flume::Receiver<LevelChunk>,
    pub cancel: &'a CancellationToken,
}

/// Builds the job's irradiance cache on `threads` threads (the engine has
/// not started, so the worker's every thread is free). Blocks: run it off
/// the async runtime.
pub fn build(
    setup: &JobSetup,
    irr: &IrradianceSetup,
    parts: Vec<Arc<Part>>,
    threads: usize,
    links: Links,
) -> anyhow::Result<(IrradianceCache, OvertureStats)> {
    if irr.measures() && !holds_everything(setup, &parts) {
        bail!("asked to measure irradiance records without holding the whole scene");
    }
    let accel = AccelSet::from_parts(parts);
    let kernel = Kernel::exact(
        &setup.materials,
        &setup.lights,
        &setup.camera,
        setup.seed,
        setup.sampler,
        setup.max_depth,
    );
    let share = Share {
        me: setup.me as usize,
        shares: &irr.shares,
        resume: irr.known,
    };
    let mut since = Instant::now();
    let exchange = |level: u32, mine: Vec<(u32, Measured)>, trace: &TraceStats| {
        if level >= irr.known {
            send(setup.job, level, &mine, trace, since.elapsed(), &links)?;
        }
        let got = receive(level, irr.params.max_records, &links);
        since = Instant::now();
        got
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads.max(1))
        .build()
        .context("the overture's threads")?;
    pool.install(|| {
        overture::run(
            &kernel,
            &WholeScene(&accel),
            irr.params,
            &irr.bounds,
            share,
            exchange,
        )
    })
}

/// Whether the parts hold every leaf of the octree.
fn holds_everything(setup: &JobSetup, parts: &[Arc<Part>]) -> bool {
    let mut held = vec![false; setup.map.owner.len()];
    for l in parts.iter().flat_map(|p| p.leaves.iter()) {
        if let Some(h) = held.get_mut(*l as usize) {
            *h = true;
        }
    }
    held.iter().all(|&h| h)
}

fn send(
    job: u64,
    level: u32,
    mine: &[(u32, Measured)],
    trace: &TraceStats,
    took: Duration,
    links: &Links,
) -> anyhow::Result<()> {
    for (records, last) in chunks(mine) {
        let c = MeasuredChunk {
            job,
            level,
            records,
            last,
            rays: if last { trace.rays() } else { 0 },
            seconds: if last { took.as_secs_f64() } else { 0.0 },
        };
        links
            .control
            .send(WorkerToScheduler::Measured(Box::new(c)))
            .context("the scheduler link closed during the overture")?;
    }
    Ok(())
}

/// Level `level` as the scheduler merged it, checked.
fn receive(level: u32, max_records: usize, links: &Links) -> anyhow::Result<Vec<Measured>> {
    let mut records = Vec::new();
    loop {
        let c = match links.levels.recv_timeout(POLL) {
            Ok(c) => c,
            Err(flume::RecvTimeoutError::Timeout) if !links.cancel.is_cancelled() => continue,
            Err(flume::RecvTimeoutError::Timeout) => {
                bail!("the job was aborted during the irradiance overture")
            }
            Err(flume::RecvTimeoutError::Disconnected) => {
                bail!("the scheduler sent more irradiance records than max_records")
            }
        };
        if c.level != level {
            bail!(
                "the scheduler sent overture level {} while level {level} was due",
                c.level
            );
        }
        if records.len() + c.records.len() > max_records {
            bail!("the scheduler sent more than {max_records} irradiance records");
        }
        for m in &c.records {
            m.check()
                .map_err(|e| anyhow::anyhow!("scheduler's overture level {level}: {e}"))?;
        }
        records.extend(c.records);
        if c.last {
            return Ok(records);
        }
    }
}
