//! The local farm: a scheduler in this process and N workers, linked over
//! real loopback TCP with the same code the daemons run. The workers run
//! in this process too (the embedded farm of `render --workers N`), or as
//! `locus worker` child processes, each with its own memory budget, whose
//! CPU time and peak memory are then measured from their own processes
//! (`bench-farm`, the memory tests). Jobs are handed to the scheduler
//! in-process, so the scene is read once and never copied or re-parsed on
//! its way in.

use anyhow::Context;
use locus_protocol::handshake::Credentials;
use locus_protocol::submit::{JobRequest, JobResult};
use locus_protocol::tls::{Tls, TlsFiles};
use locus_scheduler::{Scheduler, SchedulerConfig, SchedulerHandle, client};
use locus_worker::builds::SharedBuilds;
use locus_worker::{Worker, WorkerConfig};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

pub struct LocalFarm {
    pub scheduler: SocketAddr,
    /// The status page's address, when the spec asked for one.
    pub http: Option<SocketAddr>,
    pub token: String,
    /// The farm's TLS, when its spec turned it on.
    pub tls: Option<Tls>,
    handle: SchedulerHandle,
    workers: usize,
    shutdown: CancellationToken,
    tasks: Vec<JoinHandle<anyhow::Result<()>>>,
    children: Vec<Child>,
}

/// What a local farm is made of.
#[derive(Clone, Debug)]
pub struct FarmSpec {
    pub workers: usize,
    pub threads_per_worker: usize,
    /// Each worker's memory budget in bytes (0: none).
    pub memory_budget: u64,
    /// Run each worker as a child process of this `locus` executable.
    pub processes: Option<PathBuf>,
    /// Where the scheduler serves its status page and metrics, if at all.
    pub http: Option<String>,
    /// TLS on every link of the farm (None: plain TCP on loopback).
    pub tls: Option<TlsFiles>,
    /// Whether workers in this process build a BVH they all hold once,
    /// for all of them ([`SharedBuilds`]). Without, each takes the
    /// scheduler's layout of a replicated region as a daemon does.
    pub shared_builds: bool,
}

impl FarmSpec {
    /// Workers in this process, without budgets or a status page.
    pub fn embedded(workers: usize, threads_per_worker: usize) -> Self {
        Self {
            workers,
            threads_per_worker,
            memory_budget: 0,
            processes: None,
            http: None,
            tls: None,
            shared_builds: true,
        }
    }
}

/// The flags that give a worker process the TLS files `f`.
fn tls_args(f: &TlsFiles) -> Vec<std::ffi::OsString> {
    let mut v = Vec::new();
    let mut flag = |name: &str, value: Option<&std::ffi::OsStr>| {
        if let Some(x) = value {
            v.push(name.into());
            v.push(x.to_os_string());
        }
    };
    flag("--tls-cert", f.cert.as_deref().map(|p| p.as_os_str()));
    flag("--tls-key", f.key.as_deref().map(|p| p.as_os_str()));
    flag("--tls-ca", f.ca.as_deref().map(|p| p.as_os_str()));
    flag(
        "--tls-server-name",
        f.server_name.as_deref().map(std::ffi::OsStr::new),
    );
    v
}

/// A worker child process, killed when dropped.
struct Child(std::process::Child);

impl Drop for Child {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A token nobody else knows: the embedded farm listens on loopback only,
/// but other local users could still connect.
fn fresh_token() -> String {
    let mut b = [0u8; 16];
    if getrandom::fill(&mut b).is_err() {
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        b[..8].copy_from_slice(
            &locus_core::sampler::mix64(t ^ std::process::id() as u64).to_le_bytes(),
        );
    }
    b.iter().map(|x| format!("{x:02x}")).collect()
}

impl LocalFarm {
    /// Starts a scheduler and `workers` workers, each tracing on
    /// `threads_per_worker` threads, all on 127.0.0.1 with OS-chosen ports.
    pub async fn start(workers: usize, threads_per_worker: usize) -> anyhow::Result<Self> {
        Self::launch(&FarmSpec::embedded(workers, threads_per_worker)).await
    }

    /// Starts the farm `spec` describes.
    pub async fn launch(spec: &FarmSpec) -> anyhow::Result<Self> {
        let (workers, threads_per_worker) = (spec.workers, spec.threads_per_worker);
        let token = fresh_token();
        let tls = match &spec.tls {
            Some(f) => Tls::load(f, true)?,
            None => None,
        };
        let shutdown = CancellationToken::new();
        let sched = Scheduler::bind(SchedulerConfig {
            listen: "127.0.0.1:0".into(),
            token: token.clone(),
            tls: tls.clone(),
            max_queued_jobs: 16,
            http: spec.http.clone(),
            worker_timeout: locus_scheduler::WORKER_TIMEOUT,
            state: None,
        })
        .await?;
        let http = sched.http_addr();
        if let Some(a) = http {
            tracing::info!("watch the farm at http://{a}/");
        }
        let addr = sched.local_addr()?;
        let handle = sched.handle();
        let mut tasks = vec![tokio::spawn(sched.run(shutdown.clone()))];
        let mut children = Vec::new();
        if let Some(exe) = &spec.processes {
            for i in 0..workers {
                let mut c = std::process::Command::new(exe);
                c.args([
                    "worker",
                    "--scheduler",
                    &addr.to_string(),
                    "--listen",
                    "127.0.0.1:0",
                ])
                .args(["--threads", &threads_per_worker.max(1).to_string()])
                .env("LOCUS_TOKEN", &token)
                .stdout(std::process::Stdio::null());
                if spec.memory_budget > 0 {
                    c.args(["--memory-budget", &spec.memory_budget.to_string()]);
                }
                if let Some(f) = &spec.tls {
                    c.args(tls_args(f));
                }
                if std::env::var_os("RUST_LOG").is_none() {
                    c.env("RUST_LOG", "warn");
                }
                let child = c
                    .spawn()
                    .with_context(|| format!("starting worker {i}: {}", exe.display()))?;
                children.push(Child(child));
            }
            return Ok(Self {
                scheduler: addr,
                http,
                token,
                tls,
                handle,
                workers,
                shutdown,
                tasks,
                children,
            });
        }
        // The workers build a part they all hold (every part, when the job
        // replicates the scene) once, on all their threads.
        let builds = match spec.shared_builds {
            true => Some(Arc::new(SharedBuilds::new(
                workers * threads_per_worker.max(1),
            )?)),
            false => None,
        };
        for i in 0..workers {
            let w = Worker::bind(WorkerConfig {
                scheduler: addr.to_string(),
                listen: "127.0.0.1:0".into(),
                advertise: None,
                token: token.clone(),
                tls: tls.clone(),
                threads: threads_per_worker.max(1),
                memory_budget: spec.memory_budget,
                name: format!("embedded-{i}"),
                dedicated: false,
                builds: builds.clone(),
            })
            .await?;
            tasks.push(tokio::spawn(w.run(shutdown.clone())));
        }
        Ok(Self {
            scheduler: addr,
            http,
            token,
            tls,
            handle,
            workers,
            shutdown,
            tasks,
            children,
        })
    }

    /// What a client of this farm connects with.
    pub fn credentials(&self) -> Credentials {
        Credentials::new(&self.token, self.tls.clone())
    }

    pub fn shutdown_token(&self) -> CancellationToken {
        self.shutdown.clone()
    }

    /// Runs one job. A job asking for "every worker" (0) gets all of this
    /// farm's: workers register a moment after `start` returns, and the
    /// scheduler would otherwise start the job with those registered so far.
    pub async fn render(
        &self,
        mut req: JobRequest,
        progress: &(dyn Fn(u64, u64) + Sync),
    ) -> anyhow::Result<JobResult> {
        if req.options.workers == 0 {
            req.options.workers = self.workers as u32;
        }
        let mut collect = client::Collector::for_request(&req);
        let mut rx = self.handle.submit(req).await?;
        loop {
            if let Some(r) = collect.take(rx.recv().await, progress) {
                return r;
            }
        }
    }

    /// Stops the worker processes, then cancels every task and waits for
    /// them. The processes go first: with the scheduler gone first they
    /// would warn, each, that it refused them as they tried to register
    /// again.
    pub async fn stop(self) -> anyhow::Result<()> {
        drop(self.children);
        self.shutdown.cancel();
        for t in self.tasks {
            t.await.context("farm task panicked")??;
        }
        Ok(())
    }
}

/// Runs one job on a fresh embedded farm in its own runtime.
pub fn render_embedded(
    req: JobRequest,
    spec: &FarmSpec,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> anyhow::Result<JobResult> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async {
        let farm = LocalFarm::launch(spec).await?;
        crate::cancel_on_signals(farm.shutdown_token());
        let r = tokio::select! {
            r = farm.render(req, progress) => r,
            _ = farm.shutdown.cancelled() => Err(anyhow::anyhow!("interrupted")),
        };
        farm.stop().await?;
        r
    })
}
