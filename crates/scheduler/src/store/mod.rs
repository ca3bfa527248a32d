//! The scheduler's state on disk (`--state DIR`): every job not yet ended,
//! with its request, and every tile of it already in the film (the passes
//! in and its pixels' sums over them), in an
//! embedded redb database. A scheduler restarted on the same directory
//! queues those jobs again with their tiles in place, renders only the
//! tiles missing, and sends the image to the client that attaches. The
//! last finished results are kept too ([`results`]), so a client that
//! attaches after a restart still gets an image finished before it.
//!
//! Writes go through a bounded channel to one thread of their own, which
//! commits whatever has arrived in one transaction, so the actor never
//! waits for the disk. A write that finds the channel full is dropped and
//! counted: a tile not stored is rendered again after a restart, never
//! wrong. The thread commits at most every [`COMMIT_EVERY`] unless a
//! client waits on the commit, and a tile written twice in that time is
//! stored once ([`Batch`]): every commit syncs the file, and committing
//! each tile pass as it came synced it 655 times in a 3-second job on the
//! generated room (32 times now, `strace -c`), CPU its workers lost.

mod results;

pub use results::Kept;

use crate::film::{PassSpread, TileSums};
use locus_core::image_io::Image;
use locus_protocol::report::FarmReport;
use locus_protocol::submit::JobRequest;
use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, oneshot};
use tracing::{info, warn};

/// Job id to its request (postcard, triangles included).
const JOBS: TableDefinition<u64, &[u8]> = TableDefinition::new("jobs");
/// (job, tile) to the tile's passes in and pixel sums ([`TileSums`],
/// postcard).
const TILES: TableDefinition<(u64, u32), &[u8]> = TableDefinition::new("tile_sums");
/// Job id to its open spread pass ([`PassSpread`], postcard), for a job
/// with adaptive sampling once one is open.
const SPREADS: TableDefinition<u64, &[u8]> = TableDefinition::new("spreads");
/// "next_job": the next job id, so ids are never reused across restarts.
const META: TableDefinition<&str, u64> = TableDefinition::new("meta");

/// Writes queued for the store's thread, and the most one commit takes.
const QUEUE: usize = 4096;

/// The least time between two commits while no client waits on one: a
/// scheduler that dies loses at most this long's tiles, which a restart
/// renders again.
pub const COMMIT_EVERY: Duration = Duration::from_millis(100);

/// How often the writer takes what has arrived while it waits to commit,
/// so that the channel holds no more than this long's writes.
const DRAIN_EVERY: Duration = Duration::from_millis(10);

pub enum Write {
    /// A job taken, with its request encoded (postcard) where it arrived.
    Job { id: u64, request: Vec<u8> },
    /// A tile's state in the film, replacing what was kept of it.
    Tile { job: u64, tile: u32, sums: TileSums },
    /// The spread of a pass that opened, replacing the one before.
    Spread { job: u64, spread: PassSpread },
    /// The job ended (done, failed, cancelled): forget it.
    End { job: u64 },
    /// A job's result, kept for clients that attach late (the last
    /// [`crate::actor::FINISHED_KEPT`] are).
    Finished {
        job: u64,
        image: Arc<Image>,
        report: Arc<FarmReport>,
        /// With adaptive sampling, each pixel's samples.
        counts: Option<Arc<Vec<u32>>>,
    },
    /// Answered once every write before it is committed (or dropped if a
    /// commit fails), so a job's client is told it is done only when its
    /// result would outlive a restart.
    Synced(oneshot::Sender<()>),
}

/// A job found in the store at start.
pub struct Restored {
    pub id: u64,
    pub req: Box<JobRequest>,
    pub tiles: Vec<(u32, TileSums)>,
    /// The open pass's spread, with adaptive sampling.
    pub spread: Option<PassSpread>,
}

/// The actor's handle: sends writes, never waits.
#[derive(Clone)]
pub struct Store {
    tx: mpsc::Sender<Write>,
    dropped: Arc<AtomicU64>,
}

impl Store {
    /// Opens (or creates) the database in `dir`, reads what it holds and
    /// starts the writer thread. Returns the handle, the next job id, the
    /// jobs to resume, and the finished results kept, oldest first.
    pub fn open(dir: &Path) -> anyhow::Result<(Self, u64, Vec<Restored>, Vec<Kept>)> {
        use anyhow::Context;
        std::fs::create_dir_all(dir)
            .with_context(|| format!("state directory {}", dir.display()))?;
        let path = dir.join("locus-scheduler.redb");
        let db = Database::create(&path)
            .with_context(|| format!("opening the state store {}", path.display()))?;
        let (next, jobs) =
            read(&db).with_context(|| format!("reading the state store {}", path.display()))?;
        let kept = db
            .begin_read()
            .map_err(anyhow::Error::from)
            .and_then(|t| results::read(&t))
            .with_context(|| format!("reading the results in {}", path.display()))?;
        drop_old_tiles(&db)
            .with_context(|| format!("updating the state store {}", path.display()))?;
        if !jobs.is_empty() {
            info!(
                jobs = jobs.len(),
                tiles = jobs.iter().map(|j| j.tiles.len()).sum::<usize>(),
                store = %path.display(),
                "jobs restored"
            );
        }
        let (tx, rx) = mpsc::channel(QUEUE);
        std::thread::Builder::new()
            .name("locus-store".into())
            .spawn(move || writer(db, rx, path))
            .context("starting the state store's thread")?;
        let dropped = Arc::new(AtomicU64::new(0));
        Ok((Self { tx, dropped }, next, jobs, kept))
    }

    /// Queues `w`; false when the queue was full and it was dropped.
    pub fn write(&self, w: Write) -> bool {
        if self.tx.try_send(w).is_err() {
            let n = self.dropped.fetch_add(1, Relaxed) + 1;
            if n.is_power_of_two() {
                warn!(dropped = n, "the state store falls behind; writes dropped");
            }
            return false;
        }
        true
    }

    /// Resolves once everything written so far is committed; an error if
    /// the queue was full or a commit failed.
    pub fn synced(&self) -> oneshot::Receiver<()> {
        let (tx, rx) = oneshot::channel();
        self.write(Write::Synced(tx));
        rx
    }
}

/// Drops the tiles of releases before progressive passes (pixel means,
/// which cannot be resumed bit-identically); their jobs render them again.
fn drop_old_tiles(db: &Database) -> anyhow::Result<()> {
    const OLD: TableDefinition<(u64, u32), &[u8]> = TableDefinition::new("tiles");
    let txn = db.begin_write()?;
    if txn.delete_table(OLD)? {
        info!("tiles of an earlier release dropped from the state store");
    }
    txn.commit()?;
    Ok(())
}

/// Everything the store holds: the next job id and the jobs with their
/// tiles. A record that does not decode is skipped with a warning (a
/// store from another release), never a panic.
fn read(db: &Database) -> anyhow::Result<(u64, Vec<Restored>)> {
    let txn = db.begin_read()?;
    let mut next = match txn.open_table(META) {
        Ok(t) => t.get("next_job")?.map_or(1, |v| v.value()),
        Err(redb::TableError::TableDoesNotExist(_)) => 1,
        Err(e) => return Err(e.into()),
    };
    let mut jobs = BTreeMap::new();
    match txn.open_table(JOBS) {
        Ok(t) => {
            for row in t.iter()? {
                let (k, v) = row?;
                let id = k.value();
                next = next.max(id + 1);
                match postcard::from_bytes::<JobRequest>(v.value()) {
                    Ok(req) => {
                        jobs.insert(
                            id,
                            Restored {
                                id,
                                req: Box::new(req),
                                tiles: Vec::new(),
                                spread: None,
                            },
                        );
                    }
                    Err(e) => warn!(job = id, "stored job does not decode ({e}); dropped"),
                }
            }
        }
        Err(redb::TableError::TableDoesNotExist(_)) => {}
        Err(e) => return Err(e.into()),
    }
    match txn.open_table(TILES) {
        Ok(t) => {
            for row in t.iter()? {
                let (k, v) = row?;
                let (job, tile) = k.value();
                let Some(j) = jobs.get_mut(&job) else {
                    continue;
                };
                match postcard::from_bytes::<TileSums>(v.value()) {
                    Ok(p) => j.tiles.push((tile, p)),
                    Err(e) => warn!(job, tile, "stored tile does not decode ({e}); dropped"),
                }
            }
        }
        Err(redb::TableError::TableDoesNotExist(_)) => {}
        Err(e) => return Err(e.into()),
    }
    match txn.open_table(SPREADS) {
        Ok(t) => {
            for row in t.iter()? {
                let (k, v) = row?;
                let job = k.value();
                let Some(j) = jobs.get_mut(&job) else {
                    continue;
                };
                match postcard::from_bytes::<PassSpread>(v.value()) {
                    Ok(p) => j.spread = Some(p),
                    Err(e) => warn!(job, "stored spread does not decode ({e}); dropped"),
                }
            }
        }
        Err(redb::TableError::TableDoesNotExist(_)) => {}
        Err(e) => return Err(e.into()),
    }
    Ok((next, jobs.into_values().collect()))
}

/// Removes job `job`'s rows of a table keyed by (job, part).
fn remove_rows(t: &mut redb::Table<(u64, u32), &[u8]>, job: u64) -> anyhow::Result<()> {
    let keys: Vec<(u64, u32)> = t
        .range((job, 0)..=(job, u32::MAX))?
        .map(|r| r.map(|(k, _)| k.value()))
        .collect::<Result<_, _>>()?;
    for k in keys {
        t.remove(k)?;
    }
    Ok(())
}

/// The writes of one commit, in the order they came, a tile's later
/// state taking its earlier one's place (a tile's write replaces what was
/// kept of it, so only the last counts).
#[derive(Default)]
struct Batch {
    writes: Vec<Write>,
    /// Where each tile's write waits in `writes`; a job's end forgets its
    /// tiles, so that a later write of one (not expected) follows the end.
    tiles: HashMap<(u64, u32), usize>,
    /// Whether a client waits on this commit ([`Write::Synced`]).
    awaited: bool,
}

impl Batch {
    fn push(&mut self, w: Write) {
        match &w {
            Write::Tile { job, tile, .. } => {
                if let Some(&i) = self.tiles.get(&(*job, *tile)) {
                    self.writes[i] = w;
                    return;
                }
                self.tiles.insert((*job, *tile), self.writes.len());
            }
            Write::End { job } => self.tiles.retain(|k, _| k.0 != *job),
            Write::Synced(_) => self.awaited = true,
            Write::Job { .. } | Write::Spread { .. } | Write::Finished { .. } => {}
        }
        self.writes.push(w);
    }

    /// Takes what has arrived, up to [`QUEUE`] writes; whether the
    /// channel is still open.
    fn take(&mut self, rx: &mut mpsc::Receiver<Write>) -> bool {
        while self.writes.len() < QUEUE {
            match rx.try_recv() {
                Ok(w) => self.push(w),
                Err(mpsc::error::TryRecvError::Empty) => return true,
                Err(mpsc::error::TryRecvError::Disconnected) => return false,
            }
        }
        true
    }
}

/// The writer thread: takes what has arrived and commits it as one
/// transaction, at most every [`COMMIT_EVERY`] unless a client waits on
/// it, until the actor drops its handles (then at once).
fn writer(db: Database, mut rx: mpsc::Receiver<Write>, path: PathBuf) {
    let mut last: Option<Instant> = None;
    while let Some(first) = rx.blocking_recv() {
        let mut batch = Batch::default();
        batch.push(first);
        loop {
            let open = batch.take(&mut rx);
            let now = Instant::now();
            let wait = last.map_or(Duration::ZERO, |t| {
                (t + COMMIT_EVERY).saturating_duration_since(now)
            });
            if !open || batch.awaited || batch.writes.len() >= QUEUE || wait.is_zero() {
                break;
            }
            std::thread::sleep(wait.min(DRAIN_EVERY));
        }
        if let Err(e) = commit(&db, batch.writes) {
            warn!(store = %path.display(), "state store write failed: {e:#}");
        }
        last = Some(Instant::now());
    }
}

fn commit(db: &Database, batch: Vec<Write>) -> anyhow::Result<()> {
    let txn = db.begin_write()?;
    let mut acks = Vec::new();
    {
        let mut jobs = txn.open_table(JOBS)?;
        let mut tiles = txn.open_table(TILES)?;
        let mut spreads = txn.open_table(SPREADS)?;
        let mut meta = txn.open_table(META)?;
        for w in batch {
            match w {
                Write::Job { id, request } => {
                    jobs.insert(id, request.as_slice())?;
                    let next = meta.get("next_job")?.map_or(1, |v| v.value());
                    meta.insert("next_job", next.max(id + 1))?;
                }
                Write::Tile { job, tile, sums } => {
                    tiles.insert((job, tile), postcard::to_allocvec(&sums)?.as_slice())?;
                }
                Write::Spread { job, spread } => {
                    spreads.insert(job, postcard::to_allocvec(&spread)?.as_slice())?;
                }
                Write::Finished {
                    job,
                    image,
                    report,
                    counts,
                } => {
                    results::put(&txn, job, &image, &report, counts.as_deref())?;
                }
                Write::End { job } => {
                    jobs.remove(job)?;
                    spreads.remove(job)?;
                    remove_rows(&mut tiles, job)?;
                }
                Write::Synced(ack) => acks.push(ack),
            }
        }
    }
    txn.commit()?;
    for ack in acks {
        let _ = ack.send(());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(name: &str) -> Box<JobRequest> {
        let scene = crate::cornell_box();
        let mut r = crate::client::request(&scene, Default::default());
        r.name = name.into();
        Box::new(r)
    }

    /// The store in `dir` opened again, once the writer thread of the last
    /// handle dropped has committed everything and released the file.
    fn reopen(dir: &Path) -> (Store, u64, Vec<Restored>, Vec<Kept>) {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        loop {
            match Store::open(dir) {
                Ok(x) => return x,
                Err(e) if std::time::Instant::now() < deadline => {
                    let _ = e;
                    std::thread::sleep(std::time::Duration::from_millis(20));
                }
                Err(e) => panic!("{e:#}"),
            }
        }
    }

    /// A tile written twice before a commit is stored once, with its later
    /// state, where its first write stood; a job's end keeps its place
    /// among the writes, and a tile of the job written after it follows
    /// it; a waiting client marks the batch.
    #[test]
    fn a_batch_keeps_each_tiles_last_state_in_order() {
        let tile = |job: u64, tile: u32, passes: u32| Write::Tile {
            job,
            tile,
            sums: TileSums {
                passes,
                sums: Vec::new(),
                counts: Vec::new(),
            },
        };
        let mut b = Batch::default();
        for w in [
            tile(1, 0, 1),
            tile(1, 1, 1),
            tile(2, 0, 1),
            tile(1, 0, 2),
            tile(2, 0, 2),
            Write::End { job: 2 },
            tile(1, 1, 2),
            tile(2, 0, 3),
            tile(1, 0, 3),
        ] {
            b.push(w);
        }
        let order: Vec<String> = b
            .writes
            .iter()
            .map(|w| match w {
                Write::Tile { job, tile, sums } => format!("{job}/{tile}@{}", sums.passes),
                Write::End { job } => format!("end {job}"),
                _ => "other".into(),
            })
            .collect();
        assert_eq!(order, ["1/0@3", "1/1@2", "2/0@2", "end 2", "2/0@3"]);
        assert!(!b.awaited);
        let (tx, _rx) = oneshot::channel();
        b.push(Write::Synced(tx));
        assert!(b.awaited);
        assert_eq!(b.writes.len(), 6);
    }

    /// `synced` answers once the writes before it are committed, and says
    /// so with an error where nothing will commit them.
    #[test]
    fn synced_answers_after_the_commit() {
        let dir = std::env::temp_dir().join(format!("locus-synced-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let (s, ..) = Store::open(&dir).unwrap();
        s.write(Write::End { job: 9 });
        assert_eq!(s.synced().blocking_recv(), Ok(()));
        // A write whose transaction fails (a record no table takes is not
        // possible, so a closed writer stands in): the answer is an error.
        let (tx, rx) = mpsc::channel(1);
        drop(rx);
        let closed = Store {
            tx,
            dropped: Arc::default(),
        };
        assert!(closed.synced().blocking_recv().is_err());
        drop(s);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The last finished results come back after a restart, images whole
    /// (in more than one run of pixels), the older ones forgotten.
    #[test]
    fn the_last_results_survive_reopening() {
        let dir = std::env::temp_dir().join(format!("locus-results-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let n = locus_protocol::submit::RESULT_CHUNK_PIXELS + 5;
        let image = |job: u64| Image {
            width: n as u32,
            height: 1,
            pixels: (0..n).map(|i| [job as f32, i as f32, 0.5]).collect(),
        };
        {
            let (s, ..) = Store::open(&dir).unwrap();
            for job in 1..=6u64 {
                let report = FarmReport {
                    scene: format!("scene {job}"),
                    ..Default::default()
                };
                s.write(Write::Finished {
                    job,
                    image: Arc::new(image(job)),
                    report: Arc::new(report),
                    counts: (job % 2 == 0).then(|| Arc::new(vec![job as u32 + 7; n])),
                });
            }
        }
        let (_, next, _, kept) = reopen(&dir);
        let ids: Vec<u64> = kept.iter().map(|k| k.id).collect();
        assert_eq!(
            ids,
            [3, 4, 5, 6],
            "the newest {} kept",
            crate::actor::FINISHED_KEPT
        );
        for k in &kept {
            assert_eq!(k.image.pixels, image(k.id).pixels);
            assert_eq!(k.report.scene, format!("scene {}", k.id));
            let counts = (k.id % 2 == 0).then(|| vec![k.id as u32 + 7; n]);
            assert_eq!(k.counts, counts, "job {}", k.id);
        }
        assert!(next >= 1);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// What was written comes back after the store is closed and opened
    /// again: jobs in id order with their tiles, ended jobs gone, and the
    /// next id past every id handed out.
    #[test]
    fn jobs_and_tiles_survive_reopening() {
        let dir = std::env::temp_dir().join(format!("locus-store-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        {
            let (s, next, jobs, _) = Store::open(&dir).unwrap();
            assert_eq!((next, jobs.len()), (1, 0));
            s.write(Write::Job {
                id: 3,
                request: postcard::to_allocvec(&*request("a")).unwrap(),
            });
            s.write(Write::Job {
                id: 4,
                request: postcard::to_allocvec(&*request("b")).unwrap(),
            });
            // A tile's later state replaces its earlier one.
            for passes in [1, 2] {
                s.write(Write::Tile {
                    job: 3,
                    tile: 7,
                    sums: TileSums {
                        passes,
                        sums: vec![
                            locus_core::passes::Moments {
                                sum: [0.5, passes as f64, f64::MIN_POSITIVE],
                                squares: [1.5, 0.0, f64::MAX]
                            };
                            4
                        ],
                        counts: vec![passes * 3, 4, 5, 6],
                    },
                });
            }
            // A job's open spread: the later one is kept, and a job's end
            // drops its own.
            for (job, pass) in [(3, 4), (3, 5), (4, 4)] {
                s.write(Write::Spread {
                    job,
                    spread: PassSpread {
                        pass,
                        given: vec![pass; 6],
                    },
                });
            }
            s.write(Write::Tile {
                job: 4,
                tile: 1,
                sums: TileSums {
                    passes: 1,
                    sums: vec![locus_core::passes::Moments {
                        sum: [2.0; 3],
                        squares: [1.5, 0.0, f64::MAX],
                    }],
                    counts: vec![2],
                },
            });
            s.write(Write::End { job: 4 });
            // The writer thread ends once the handle is dropped and it has
            // committed everything; wait for the file to be released.
            drop(s);
        }
        let (_, next, jobs, _) = reopen(&dir);
        assert_eq!(next, 5);
        assert_eq!(jobs.len(), 1);
        assert_eq!((jobs[0].id, jobs[0].req.name.as_str()), (3, "a"));
        assert_eq!(jobs[0].req.tris, request("a").tris);
        let kept = TileSums {
            passes: 2,
            sums: vec![
                locus_core::passes::Moments {
                    sum: [0.5, 2.0, f64::MIN_POSITIVE],
                    squares: [1.5, 0.0, f64::MAX]
                };
                4
            ],
            counts: vec![6, 4, 5, 6],
        };
        assert_eq!(jobs[0].tiles, vec![(7, kept)]);
        let spread = PassSpread {
            pass: 5,
            given: vec![5; 6],
        };
        assert_eq!(jobs[0].spread, Some(spread));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
