//! Submitting a job and waiting for its result: the client side of
//! [`locus_protocol::submit`], used by `locus submit` and the embedded farm.

use anyhow::{Context, bail};
use locus_core::scene::Scene;
use locus_protocol::control::Opening;
use locus_protocol::submit::{JobOptions, JobRequest, JobResult, SchedulerToClient};
use locus_protocol::{MAX_FRAME_LEN, handshake};

/// The job for `scene`, moving its triangles rather than copying them.
pub fn request_owned(mut scene: Scene, options: JobOptions, load_s: f64) -> JobRequest {
    JobRequest {
        name: scene.path.display().to_string(),
        camera: scene.camera,
        settings: scene.settings,
        materials: scene.materials,
        tris: std::mem::take(&mut scene.tris),
        tri_material: std::mem::take(&mut scene.tri_material),
        options,
        load_s,
    }
}

/// Takes one of a job's messages: `Some` with the result (or why the job
/// failed) once it has come, `None` while it goes on. `progress(done,
/// total)` is called as tiles come in.
pub fn take(
    m: Option<SchedulerToClient>,
    progress: &(dyn Fn(u32, u32) + Sync),
) -> Option<anyhow::Result<JobResult>> {
    match m {
        Some(SchedulerToClient::Accepted { job, workers }) => {
            tracing::info!(job, workers, "job accepted");
            None
        }
        Some(SchedulerToClient::Progress {
            tiles_done, tiles, ..
        }) => {
            progress(tiles_done, tiles);
            None
        }
        Some(SchedulerToClient::Done(r)) => Some(Ok(*r)),
        Some(SchedulerToClient::Failed { job, reason }) => {
            Some(Err(anyhow::anyhow!("job {job} failed: {reason}")))
        }
        None => Some(Err(anyhow::anyhow!(
            "the scheduler went away before the job finished"
        ))),
    }
}

pub fn request(scene: &Scene, options: JobOptions) -> JobRequest {
    JobRequest {
        name: scene.path.display().to_string(),
        camera: scene.camera.clone(),
        settings: scene.settings.clone(),
        materials: scene.materials.clone(),
        tris: scene.tris.clone(),
        tri_material: scene.tri_material.clone(),
        options,
        load_s: 0.0,
    }
}

/// Submits `req` and waits for the result; `progress(done, total)` is called
/// as tiles come in.
pub async fn submit(
    scheduler: &str,
    token: &str,
    req: JobRequest,
    progress: &(dyn Fn(u32, u32) + Sync),
) -> anyhow::Result<JobResult> {
    let mut conn = handshake::dial(scheduler, token.as_bytes(), MAX_FRAME_LEN)
        .await
        .context("submit: connecting to the scheduler")?;
    let name = req.name.clone();
    conn.write_msg(&Opening::Submit(Box::new(req)))
        .await
        .with_context(|| format!("submit: sending {name}"))?;
    let peer = conn.peer();
    loop {
        let m = conn.read_msg::<SchedulerToClient>("submit").await?;
        if m.is_none() {
            bail!("scheduler {peer} closed the connection before the job finished");
        }
        if let Some(r) = take(m, progress) {
            return r;
        }
    }
}
