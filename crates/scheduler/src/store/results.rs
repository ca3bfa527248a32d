//! Finished results in the store: the last [`FINISHED_KEPT`] jobs' images
//! and reports, so that a client attaching after a restart still gets its
//! image. An image is kept in runs of [`RESULT_CHUNK_PIXELS`] pixels (one
//! record each), so no record grows with the image, and an adaptive job's
//! sample counts in runs of [`RESULT_CHUNK_COUNTS`].

use crate::actor::FINISHED_KEPT;
use locus_core::image_io::Image;
use locus_protocol::report::FarmReport;
use locus_protocol::submit::{RESULT_CHUNK_COUNTS, RESULT_CHUNK_PIXELS};
use redb::{ReadTransaction, ReadableTable, TableDefinition, WriteTransaction};
use serde::{Deserialize, Serialize};
use tracing::warn;

/// Finished job id to its result without pixels ([`Head`], postcard).
const RESULTS: TableDefinition<u64, &[u8]> = TableDefinition::new("results");
/// (job, run) to a run of its image's pixels, row-major (postcard).
const PIXELS: TableDefinition<(u64, u32), &[u8]> = TableDefinition::new("result_pixels");
/// (job, run) to a run of its pixels' sample counts, row-major (postcard).
const COUNTS: TableDefinition<(u64, u32), &[u8]> = TableDefinition::new("result_counts");

#[derive(Serialize, Deserialize)]
struct Head {
    width: u32,
    height: u32,
    report: FarmReport,
}

/// A finished result found in the store.
pub struct Kept {
    pub id: u64,
    pub image: Image,
    pub report: FarmReport,
    pub counts: Option<Vec<u32>>,
}

/// Keeps job `job`'s result, then forgets all but the newest
/// [`FINISHED_KEPT`] results.
pub(super) fn put(
    txn: &WriteTransaction,
    job: u64,
    image: &Image,
    report: &FarmReport,
    counts: Option<&Vec<u32>>,
) -> anyhow::Result<()> {
    let mut results = txn.open_table(RESULTS)?;
    let mut pixels = txn.open_table(PIXELS)?;
    let mut stored_counts = txn.open_table(COUNTS)?;
    let head = Head {
        width: image.width,
        height: image.height,
        report: report.clone(),
    };
    results.insert(job, postcard::to_allocvec(&head)?.as_slice())?;
    for (k, run) in image.pixels.chunks(RESULT_CHUNK_PIXELS).enumerate() {
        pixels.insert((job, k as u32), postcard::to_allocvec(run)?.as_slice())?;
    }
    for (k, run) in counts
        .iter()
        .flat_map(|c| c.chunks(RESULT_CHUNK_COUNTS))
        .enumerate()
    {
        stored_counts.insert((job, k as u32), postcard::to_allocvec(run)?.as_slice())?;
    }
    let ids: Vec<u64> = results
        .iter()?
        .map(|r| r.map(|(k, _)| k.value()))
        .collect::<Result<_, _>>()?;
    let old = ids.len().saturating_sub(FINISHED_KEPT);
    for &id in &ids[..old] {
        results.remove(id)?;
        super::remove_rows(&mut pixels, id)?;
        super::remove_rows(&mut stored_counts, id)?;
    }
    Ok(())
}

/// The results kept, oldest first; one that does not decode or whose
/// pixels are not all there is skipped with a warning.
pub(super) fn read(txn: &ReadTransaction) -> anyhow::Result<Vec<Kept>> {
    let (results, pixels) = match (txn.open_table(RESULTS), txn.open_table(PIXELS)) {
        (Ok(r), Ok(p)) => (r, p),
        (Err(redb::TableError::TableDoesNotExist(_)), _)
        | (_, Err(redb::TableError::TableDoesNotExist(_))) => return Ok(Vec::new()),
        (Err(e), _) | (_, Err(e)) => return Err(e.into()),
    };
    let mut kept = Vec::new();
    for row in results.iter()? {
        let (k, v) = row?;
        let id = k.value();
        let Ok(head) = postcard::from_bytes::<Head>(v.value()) else {
            warn!(job = id, "a stored result does not decode; dropped");
            continue;
        };
        let want = head.width as usize * head.height as usize;
        let mut px: Vec<[f32; 3]> = Vec::with_capacity(want.min(1 << 26));
        for run in pixels.range((id, 0)..=(id, u32::MAX))? {
            let (_, v) = run?;
            match postcard::from_bytes::<Vec<[f32; 3]>>(v.value()) {
                Ok(p) if px.len() + p.len() <= want => px.extend(p),
                _ => break,
            }
        }
        if px.len() != want {
            warn!(job = id, "a stored result's image is incomplete; dropped");
            continue;
        }
        let image = Image {
            width: head.width,
            height: head.height,
            pixels: px,
        };
        let counts = counts_of(txn, id, want)?;
        kept.push(Kept {
            id,
            image,
            report: head.report,
            counts,
        });
    }
    Ok(kept)
}

/// Job `id`'s sample counts, if it kept `want` of them (a store from before
/// they were kept has none; an incomplete set is dropped with a warning).
fn counts_of(txn: &ReadTransaction, id: u64, want: usize) -> anyhow::Result<Option<Vec<u32>>> {
    let table = match txn.open_table(COUNTS) {
        Ok(t) => t,
        Err(redb::TableError::TableDoesNotExist(_)) => return Ok(None),
        Err(e) => return Err(e.into()),
    };
    let mut counts: Vec<u32> = Vec::new();
    for run in table.range((id, 0)..=(id, u32::MAX))? {
        let (_, v) = run?;
        match postcard::from_bytes::<Vec<u32>>(v.value()) {
            Ok(c) if counts.len() + c.len() <= want => counts.extend(c),
            _ => break,
        }
    }
    if counts.is_empty() {
        return Ok(None);
    }
    if counts.len() != want {
        warn!(
            job = id,
            "a stored result's sample counts are incomplete; dropped"
        );
        return Ok(None);
    }
    Ok(Some(counts))
}
