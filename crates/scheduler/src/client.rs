//! Submitting a job and waiting for its result: the client side of
//! [`locus_protocol::submit`], used by `locus submit` and the embedded farm.

use anyhow::{Context, bail};
use glam::Vec3;
use locus_core::scene::Scene;
use locus_protocol::control::Opening;
use locus_protocol::handshake::Credentials;
use locus_protocol::submit::{
    JobKind, JobOptions, JobRequest, JobResult, REQUEST_PART_TRIANGLES, SchedulerToClient,
    TrianglePart,
};
use locus_protocol::{MAX_FRAME_LEN, handshake};
use std::time::Duration;

/// The job for `scene`, moving its triangles rather than copying them.
pub fn request_owned(mut scene: Scene, options: JobOptions, load_s: f64) -> JobRequest {
    JobRequest {
        name: scene.path.display().to_string(),
        camera: scene.camera,
        settings: scene.settings,
        materials: scene.materials,
        tris: std::mem::take(&mut scene.tris),
        tri_material: std::mem::take(&mut scene.tri_material),
        tri_normals: std::mem::take(&mut scene.tri_normals),
        options,
        load_s,
        kind: JobKind::Render,
    }
}

/// Gathers one job's messages into its result: `take` gives `Some` with
/// the result (or why the job failed) once it has come, `None` while it
/// goes on; `progress(done, total)` is called with the pixel samples in
/// the film as tiles come in. The image arrives in
/// [`SchedulerToClient::Pixels`] runs, in order, which are checked against
/// the size the job asked for, so a scheduler cannot make the client hold
/// more.
pub struct Collector {
    pixels: Vec<[f32; 3]>,
    /// With adaptive sampling, each pixel's samples, as their runs arrive
    /// (bounded as the pixels are).
    counts: Vec<u32>,
    /// Pixels the job asked for; None when attaching by id, where runs are
    /// bounded by the largest image a job may ask for and the whole is
    /// checked against the size `Done` gives.
    expected: Option<usize>,
    /// The job's id, once the scheduler has said it.
    pub job: Option<u64>,
    /// A radiosity job's meshed solution, as its runs arrive.
    pub mesh: Vec<[(Vec3, Vec3); 3]>,
    /// The most mesh triangles the job may send.
    mesh_bound: usize,
}

/// Mesh triangles a client accepts when it does not know the job's
/// element limit (attaching by id): 64 M, 4.5 GiB.
const MAX_MESH_TRIANGLES: usize = 1 << 26;

impl Collector {
    /// For a job of `width` x `height` pixels.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            pixels: Vec::new(),
            counts: Vec::new(),
            expected: Some(width as usize * height as usize),
            job: None,
            mesh: Vec::new(),
            mesh_bound: MAX_MESH_TRIANGLES,
        }
    }

    /// For `req`: its image size, and for a radiosity job its element
    /// limit as the bound on the mesh.
    pub fn for_request(req: &JobRequest) -> Self {
        let mut c = Self::new(req.camera.width, req.camera.height);
        if let JobKind::Radiosity(r) = &req.kind {
            c.mesh_bound = r.params.max_elements.min(MAX_MESH_TRIANGLES as u64) as usize;
        }
        c
    }

    /// For a job attached to by id, whose size the client does not know.
    pub fn any_size() -> Self {
        Self {
            pixels: Vec::new(),
            counts: Vec::new(),
            expected: None,
            job: None,
            mesh: Vec::new(),
            mesh_bound: MAX_MESH_TRIANGLES,
        }
    }

    /// Drops a result cut off with its link: an attached link sends the
    /// whole image again.
    pub fn reattached(&mut self) {
        self.pixels = Vec::new();
        self.counts = Vec::new();
        self.mesh = Vec::new();
    }

    pub fn take(
        &mut self,
        m: Option<SchedulerToClient>,
        progress: &(dyn Fn(u64, u64) + Sync),
    ) -> Option<anyhow::Result<JobResult>> {
        match m {
            Some(SchedulerToClient::Queued { job, ahead }) => {
                tracing::info!(job, ahead, "job queued");
                self.job = Some(job);
                None
            }
            Some(SchedulerToClient::Accepted { job, workers }) => {
                tracing::info!(job, workers, "job accepted");
                self.job = Some(job);
                None
            }
            Some(SchedulerToClient::Progress {
                samples_done,
                samples,
                ..
            }) => {
                progress(samples_done, samples);
                None
            }
            Some(SchedulerToClient::Pixels {
                job,
                offset,
                pixels,
            }) => {
                let bound = self.expected.unwrap_or(MAX_IMAGE_PIXELS);
                append_run(&mut self.pixels, offset, &pixels, bound)
                    .map(|e| Err(anyhow::anyhow!("job {job}: pixels {e}")))
            }
            Some(SchedulerToClient::Counts {
                job,
                offset,
                counts,
            }) => {
                let bound = self.expected.unwrap_or(MAX_IMAGE_PIXELS);
                append_run(&mut self.counts, offset, &counts, bound)
                    .map(|e| Err(anyhow::anyhow!("job {job}: sample counts {e}")))
            }
            Some(SchedulerToClient::Mesh { job, offset, tris }) => {
                append_run(&mut self.mesh, offset, &tris, self.mesh_bound)
                    .map(|e| Err(anyhow::anyhow!("job {job}: mesh triangles {e}")))
            }
            Some(SchedulerToClient::Done(r)) => {
                let mut r = *r;
                if r.pixels.is_empty() {
                    r.pixels = std::mem::take(&mut self.pixels);
                }
                if let Some(rad) = r.radiosity.as_mut() {
                    rad.mesh = std::mem::take(&mut self.mesh);
                }
                let want = self
                    .expected
                    .unwrap_or(r.width as usize * r.height as usize);
                if r.pixels.len() != want {
                    return Some(Err(anyhow::anyhow!(
                        "job {}: the image has {} pixels, {want} were asked for",
                        r.job,
                        r.pixels.len(),
                    )));
                }
                if r.sample_counts.is_none() && !self.counts.is_empty() {
                    r.sample_counts = Some(std::mem::take(&mut self.counts));
                }
                if let Some(c) = &r.sample_counts
                    && c.len() != want
                {
                    return Some(Err(anyhow::anyhow!(
                        "job {}: {} sample counts for {want} pixels",
                        r.job,
                        c.len(),
                    )));
                }
                Some(Ok(r))
            }
            Some(SchedulerToClient::Failed { job, reason }) => {
                Some(Err(anyhow::anyhow!("job {job} failed: {reason}")))
            }
            None => Some(Err(anyhow::anyhow!(
                "the scheduler went away before the job finished"
            ))),
        }
    }
}

/// Appends a result's run `run`, said to start at `offset`, to `to`, if it
/// follows what came and keeps within `bound` items; otherwise says what
/// arrived after what ("3..5 arrived after 4 of 6").
fn append_run<T: Clone>(to: &mut Vec<T>, offset: u64, run: &[T], bound: usize) -> Option<String> {
    if offset != to.len() as u64 || to.len() + run.len() > bound {
        return Some(format!(
            "{offset}..{} arrived after {} of {bound}",
            offset + run.len() as u64,
            to.len(),
        ));
    }
    to.extend_from_slice(run);
    None
}

pub fn request(scene: &Scene, options: JobOptions) -> JobRequest {
    JobRequest {
        name: scene.path.display().to_string(),
        camera: scene.camera.clone(),
        settings: scene.settings.clone(),
        materials: scene.materials.clone(),
        tris: scene.tris.clone(),
        tri_material: scene.tri_material.clone(),
        tri_normals: scene.tri_normals.clone(),
        options,
        load_s: 0.0,
        kind: JobKind::Render,
    }
}

/// The most pixels an image may have (32768 x 32768, the largest a job
/// may ask for).
const MAX_IMAGE_PIXELS: usize = 1 << 30;

/// Submits `req` to run detached (it runs on without this client) and
/// returns its id once the scheduler has taken it.
pub async fn submit_detached(
    scheduler: &str,
    creds: impl Into<Credentials>,
    mut req: JobRequest,
) -> anyhow::Result<u64> {
    req.options.detached = true;
    let name = req.name.clone();
    let mut conn = send_request(scheduler, &creds.into(), req, REQUEST_PART_TRIANGLES).await?;
    loop {
        match conn.read_msg::<SchedulerToClient>("submit").await? {
            Some(SchedulerToClient::Queued { job, .. }) => return Ok(job),
            Some(SchedulerToClient::Failed { reason, .. }) => bail!("{name} refused: {reason}"),
            Some(_) => {}
            None => bail!("the scheduler closed the connection before taking {name}"),
        }
    }
}

/// Attaches to job `job` (submitted detached, or whose client went away
/// with the scheduler) and waits for its result, taking the job up again
/// if the link breaks, as [`submit`] does.
pub async fn attach_to(
    scheduler: &str,
    creds: impl Into<Credentials>,
    job: u64,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> anyhow::Result<JobResult> {
    let creds = &creds.into();
    let mut collect = Collector::any_size();
    collect.job = Some(job);
    let mut conn = attach(scheduler, creds, job).await?;
    loop {
        match follow(&mut conn, &mut collect, progress).await {
            Ok(r) => return r,
            Err(broke) => {
                tracing::warn!(job, "{broke:#}; attaching to the job again");
                conn = attach(scheduler, creds, job).await?;
                collect.reattached();
            }
        }
    }
}

/// How long a client whose link broke after its job was taken (the
/// scheduler restarting, a network blip) keeps trying to attach to it.
pub const REATTACH_WINDOW: Duration = Duration::from_secs(300);

/// Submits `req` and waits for the result; `progress(done, total)` is called
/// with the pixel samples in as tiles come in. A link that breaks once the
/// job has its id is taken up again ([`Opening::Attach`]) for up to
/// [`REATTACH_WINDOW`], retrying with backoff: a scheduler restarted on
/// its state directory resumes the job. `creds` is the token (plain TCP)
/// or [`Credentials`] with TLS.
pub async fn submit(
    scheduler: &str,
    creds: impl Into<Credentials>,
    req: JobRequest,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> anyhow::Result<JobResult> {
    submit_in_parts_of(scheduler, creds, req, progress, REQUEST_PART_TRIANGLES).await
}

/// As [`submit`], sending the triangles in parts of `part` (a request of
/// at most `part` triangles goes in one frame).
pub async fn submit_in_parts_of(
    scheduler: &str,
    creds: impl Into<Credentials>,
    req: JobRequest,
    progress: &(dyn Fn(u64, u64) + Sync),
    part: usize,
) -> anyhow::Result<JobResult> {
    let creds = &creds.into();
    let mut collect = Collector::for_request(&req);
    let mut conn = send_request(scheduler, creds, req, part).await?;
    loop {
        let broke = match follow(&mut conn, &mut collect, progress).await {
            Ok(r) => return r,
            Err(e) => e,
        };
        let Some(job) = collect.job else {
            return Err(broke.context("the link to the scheduler broke before it took the job"));
        };
        tracing::warn!(job, "{broke:#}; attaching to the job again");
        conn = attach(scheduler, creds, job).await.with_context(|| {
            format!(
                "job {job}: the link to the scheduler broke ({broke:#}) and attaching again failed"
            )
        })?;
        collect.reattached();
    }
}

/// Connects and sends `req`: in one frame when it has at most `part`
/// triangles, else its settings first and its triangles in parts of
/// `part`, so a scene of any size fits the frame limit.
async fn send_request(
    scheduler: &str,
    creds: &Credentials,
    mut req: JobRequest,
    part: usize,
) -> anyhow::Result<locus_protocol::Connection> {
    let mut conn = handshake::dial(scheduler, creds, MAX_FRAME_LEN)
        .await
        .context("submit: connecting to the scheduler")?;
    let name = req.name.clone();
    let sending = || format!("submit: sending {name}");
    // Shading normals nearly double a triangle: half as many per part.
    let part = if req.tri_normals.is_empty() {
        part.max(1)
    } else {
        (part / 2).max(1)
    };
    if req.tris.len() <= part {
        conn.write_msg(&Opening::Submit(Box::new(req)))
            .await
            .with_context(sending)?;
        return Ok(conn);
    }
    let tris = std::mem::take(&mut req.tris);
    let material = std::mem::take(&mut req.tri_material);
    let normals = std::mem::take(&mut req.tri_normals);
    conn.write_msg(&Opening::SubmitInParts {
        request: Box::new(req),
        triangles: tris.len() as u64,
        normals: !normals.is_empty(),
    })
    .await
    .with_context(sending)?;
    for (k, (t, m)) in tris.chunks(part).zip(material.chunks(part)).enumerate() {
        let p = TrianglePart {
            tris: t.to_vec(),
            material: m.to_vec(),
            normals: normals
                .chunks(part)
                .nth(k)
                .map_or_else(Vec::new, <[_]>::to_vec),
        };
        conn.write_msg(&p).await.with_context(sending)?;
    }
    Ok(conn)
}

/// Reads the job's messages until its result (or failure); an error is the
/// link breaking.
async fn follow(
    conn: &mut locus_protocol::Connection,
    collect: &mut Collector,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> anyhow::Result<anyhow::Result<JobResult>> {
    let peer = conn.peer();
    loop {
        let m = conn.read_msg::<SchedulerToClient>("submit").await?;
        if m.is_none() {
            bail!("scheduler {peer} closed the connection before the job finished");
        }
        if let Some(r) = collect.take(m, progress) {
            return Ok(r);
        }
    }
}

/// Attaches to `job`, retrying while the scheduler cannot be reached, for
/// up to [`REATTACH_WINDOW`]; a refused handshake is final.
async fn attach(
    scheduler: &str,
    creds: &Credentials,
    job: u64,
) -> anyhow::Result<locus_protocol::Connection> {
    let deadline = tokio::time::Instant::now() + REATTACH_WINDOW;
    let mut backoff = locus_protocol::Backoff::default();
    loop {
        let e = match handshake::dial(scheduler, creds, MAX_FRAME_LEN).await {
            Ok(mut c) => match c.write_msg(&Opening::Attach { job }).await {
                Ok(_) => return Ok(c),
                Err(e) => e,
            },
            Err(e) => e,
        };
        let wait = backoff.next_delay();
        if e.is_refusal() || tokio::time::Instant::now() + wait > deadline {
            return Err(e.into());
        }
        tokio::time::sleep(wait).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use locus_protocol::report::FarmReport;

    fn pixels(offset: u64, n: usize) -> Option<SchedulerToClient> {
        Some(SchedulerToClient::Pixels {
            job: 1,
            offset,
            pixels: (0..n).map(|i| [(offset as usize + i) as f32; 3]).collect(),
        })
    }

    fn done() -> Option<SchedulerToClient> {
        Some(SchedulerToClient::Done(Box::new(JobResult {
            job: 1,
            width: 3,
            height: 2,
            pixels: Vec::new(),
            report: FarmReport::default(),
            sample_counts: None,
            radiosity: None,
        })))
    }

    /// Runs in order make the image; a gap, an overlap, a run past the
    /// size asked for, or an image short of it is an error.
    #[test]
    fn chunks_assemble_in_order_within_the_size_asked_for() {
        let none = &|_, _| {};
        let mut c = Collector::new(3, 2);
        assert!(c.take(pixels(0, 4), none).is_none());
        assert!(c.take(pixels(4, 2), none).is_none());
        let r = c.take(done(), none).unwrap().unwrap();
        let firsts: Vec<f32> = r.pixels.iter().map(|p| p[0]).collect();
        assert_eq!(firsts, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        for (a, b) in [(0, 5), (3, 3)] {
            let mut c = Collector::new(3, 2);
            assert!(c.take(pixels(0, 4), none).is_none());
            let e = c.take(pixels(a, b), none).unwrap().unwrap_err();
            assert!(e.to_string().contains("arrived after 4 of 6"), "{e}");
        }
        let mut c = Collector::new(3, 2);
        assert!(c.take(pixels(0, 5), none).is_none());
        let e = c.take(done(), none).unwrap().unwrap_err();
        assert!(e.to_string().contains("5 pixels, 6 were asked"), "{e}");
    }

    fn counts(offset: u64, n: usize) -> Option<SchedulerToClient> {
        Some(SchedulerToClient::Counts {
            job: 1,
            offset,
            counts: (0..n as u32).map(|i| offset as u32 + i + 8).collect(),
        })
    }

    /// An adaptive job's sample counts arrive in runs after the image, as
    /// its pixels do, and must number the pixels.
    #[test]
    fn sample_counts_assemble_like_the_pixels() {
        let none = &|_, _| {};
        let mut c = Collector::new(3, 2);
        for m in [pixels(0, 6), counts(0, 2), counts(2, 4)] {
            assert!(c.take(m, none).is_none());
        }
        let r = c.take(done(), none).unwrap().unwrap();
        assert_eq!(r.sample_counts, Some(vec![8, 9, 10, 11, 12, 13]));
        let mut c = Collector::new(3, 2);
        assert!(c.take(counts(0, 4), none).is_none());
        let e = c.take(counts(5, 1), none).unwrap().unwrap_err();
        assert!(e.to_string().contains("arrived after 4 of 6"), "{e}");
        let mut c = Collector::new(3, 2);
        for m in [pixels(0, 6), counts(0, 5)] {
            assert!(c.take(m, none).is_none());
        }
        let e = c.take(done(), none).unwrap().unwrap_err();
        assert!(e.to_string().contains("5 sample counts for 6"), "{e}");
        // An even job sends none.
        let mut c = Collector::new(3, 2);
        assert!(c.take(pixels(0, 6), none).is_none());
        assert_eq!(c.take(done(), none).unwrap().unwrap().sample_counts, None);
    }
}
