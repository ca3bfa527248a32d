//! Submitting a job and waiting for its result: the client side of
//! [`locus_protocol::submit`], used by `locus submit` and the embedded farm.

use anyhow::{Context, bail};
use locus_core::scene::Scene;
use locus_protocol::control::Opening;
use locus_protocol::submit::{JobOptions, JobRequest, JobResult, SchedulerToClient};
use locus_protocol::{MAX_FRAME_LEN, handshake};

pub fn request(scene: &Scene, options: JobOptions) -> JobRequest {
    JobRequest {
        name: scene.path.display().to_string(),
        camera: scene.camera.clone(),
        settings: scene.settings.clone(),
        materials: scene.materials.clone(),
        tris: scene.tris.clone(),
        tri_material: scene.tri_material.clone(),
        options,
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
    loop {
        match conn.read_msg::<SchedulerToClient>("submit").await? {
            Some(SchedulerToClient::Accepted { job, workers }) => {
                tracing::info!(job, workers, "job accepted")
            }
            Some(SchedulerToClient::Progress {
                tiles_done, tiles, ..
            }) => progress(tiles_done, tiles),
            Some(SchedulerToClient::Done(r)) => return Ok(*r),
            Some(SchedulerToClient::Failed { job, reason }) => bail!("job {job} failed: {reason}"),
            None => bail!(
                "scheduler {} closed the connection before the job finished",
                conn.peer()
            ),
        }
    }
}
