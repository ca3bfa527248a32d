//! The scheduler's state on disk (`--state DIR`): every job not yet ended,
//! with its request, and every tile of it already in the film, in an
//! embedded redb database. A scheduler restarted on the same directory
//! queues those jobs again with their tiles in place, renders only the
//! tiles missing, and sends the image to the client that attaches.
//!
//! Writes go through a bounded channel to one thread of their own, which
//! commits whatever has arrived in one transaction, so the actor never
//! waits for the disk. A write that finds the channel full is dropped and
//! counted: a tile not stored is rendered again after a restart, never
//! wrong.

use locus_protocol::submit::JobRequest;
use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use tokio::sync::mpsc;
use tracing::{info, warn};

/// Job id to its request (postcard, triangles included).
const JOBS: TableDefinition<u64, &[u8]> = TableDefinition::new("jobs");
/// (job, tile) to the tile's pixels (postcard).
const TILES: TableDefinition<(u64, u32), &[u8]> = TableDefinition::new("tiles");
/// "next_job": the next job id, so ids are never reused across restarts.
const META: TableDefinition<&str, u64> = TableDefinition::new("meta");

/// Writes queued for the store's thread.
const QUEUE: usize = 4096;

pub enum Write {
    Job {
        id: u64,
        req: Box<JobRequest>,
    },
    Tile {
        job: u64,
        tile: u32,
        pixels: Vec<[f32; 3]>,
    },
    /// The job ended (done, failed, cancelled): forget it.
    End {
        job: u64,
    },
}

/// A job found in the store at start.
pub struct Restored {
    pub id: u64,
    pub req: Box<JobRequest>,
    pub tiles: Vec<(u32, Vec<[f32; 3]>)>,
}

/// The actor's handle: sends writes, never waits.
#[derive(Clone)]
pub struct Store {
    tx: mpsc::Sender<Write>,
    dropped: Arc<AtomicU64>,
}

impl Store {
    /// Opens (or creates) the database in `dir`, reads what it holds and
    /// starts the writer thread. Returns the handle, the next job id and
    /// the jobs to resume, oldest first.
    pub fn open(dir: &Path) -> anyhow::Result<(Self, u64, Vec<Restored>)> {
        use anyhow::Context;
        std::fs::create_dir_all(dir)
            .with_context(|| format!("state directory {}", dir.display()))?;
        let path = dir.join("locus-scheduler.redb");
        let db = Database::create(&path)
            .with_context(|| format!("opening the state store {}", path.display()))?;
        let (next, jobs) =
            read(&db).with_context(|| format!("reading the state store {}", path.display()))?;
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
        Ok((Self { tx, dropped }, next, jobs))
    }

    pub fn write(&self, w: Write) {
        if self.tx.try_send(w).is_err() {
            let n = self.dropped.fetch_add(1, Relaxed) + 1;
            if n.is_power_of_two() {
                warn!(dropped = n, "the state store falls behind; writes dropped");
            }
        }
    }
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
                match postcard::from_bytes::<Vec<[f32; 3]>>(v.value()) {
                    Ok(p) => j.tiles.push((tile, p)),
                    Err(e) => warn!(job, tile, "stored tile does not decode ({e}); dropped"),
                }
            }
        }
        Err(redb::TableError::TableDoesNotExist(_)) => {}
        Err(e) => return Err(e.into()),
    }
    Ok((next, jobs.into_values().collect()))
}

/// The writer thread: takes what has arrived and commits it as one
/// transaction, until the actor drops its handles.
fn writer(db: Database, mut rx: mpsc::Receiver<Write>, path: PathBuf) {
    while let Some(first) = rx.blocking_recv() {
        let mut batch = vec![first];
        while batch.len() < QUEUE {
            match rx.try_recv() {
                Ok(w) => batch.push(w),
                Err(_) => break,
            }
        }
        if let Err(e) = commit(&db, batch) {
            warn!(store = %path.display(), "state store write failed: {e:#}");
        }
    }
}

fn commit(db: &Database, batch: Vec<Write>) -> anyhow::Result<()> {
    let txn = db.begin_write()?;
    {
        let mut jobs = txn.open_table(JOBS)?;
        let mut tiles = txn.open_table(TILES)?;
        let mut meta = txn.open_table(META)?;
        for w in batch {
            match w {
                Write::Job { id, req } => {
                    jobs.insert(id, postcard::to_allocvec(&*req)?.as_slice())?;
                    let next = meta.get("next_job")?.map_or(1, |v| v.value());
                    meta.insert("next_job", next.max(id + 1))?;
                }
                Write::Tile { job, tile, pixels } => {
                    tiles.insert((job, tile), postcard::to_allocvec(&pixels)?.as_slice())?;
                }
                Write::End { job } => {
                    jobs.remove(job)?;
                    let keys: Vec<(u64, u32)> = tiles
                        .range((job, 0)..=(job, u32::MAX))?
                        .map(|r| r.map(|(k, _)| k.value()))
                        .collect::<Result<_, _>>()?;
                    for k in keys {
                        tiles.remove(k)?;
                    }
                }
            }
        }
    }
    txn.commit()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(name: &str) -> Box<JobRequest> {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let scene =
            locus_core::scene::Scene::load(&root.join("scenes/cornell-box/cornell.toml")).unwrap();
        let mut r = crate::client::request(&scene, Default::default());
        r.name = name.into();
        Box::new(r)
    }

    /// What was written comes back after the store is closed and opened
    /// again: jobs in id order with their tiles, ended jobs gone, and the
    /// next id past every id handed out.
    #[test]
    fn jobs_and_tiles_survive_reopening() {
        let dir = std::env::temp_dir().join(format!("locus-store-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        {
            let (s, next, jobs) = Store::open(&dir).unwrap();
            assert_eq!((next, jobs.len()), (1, 0));
            s.write(Write::Job {
                id: 3,
                req: request("a"),
            });
            s.write(Write::Job {
                id: 4,
                req: request("b"),
            });
            s.write(Write::Tile {
                job: 3,
                tile: 7,
                pixels: vec![[0.5, 1.0, f32::MIN_POSITIVE]; 4],
            });
            s.write(Write::Tile {
                job: 4,
                tile: 1,
                pixels: vec![[2.0; 3]],
            });
            s.write(Write::End { job: 4 });
            // The writer thread ends once the handle is dropped and it has
            // committed everything; wait for the file to be released.
            drop(s);
        }
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        let (next, jobs) = loop {
            match Store::open(&dir) {
                Ok((_, n, j)) => break (n, j),
                Err(e) if std::time::Instant::now() < deadline => {
                    let _ = e;
                    std::thread::sleep(std::time::Duration::from_millis(20));
                }
                Err(e) => panic!("{e:#}"),
            }
        };
        assert_eq!(next, 5);
        assert_eq!(jobs.len(), 1);
        assert_eq!((jobs[0].id, jobs[0].req.name.as_str()), (3, "a"));
        assert_eq!(jobs[0].req.tris, request("a").tris);
        assert_eq!(
            jobs[0].tiles,
            vec![(7, vec![[0.5, 1.0, f32::MIN_POSITIVE]; 4])]
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
