//! Does tracing and shading one path at a time cost more than the two
//! apart? (The error-per-second issue's question about a wavefront; not a
//! feature.)
//!
//! Renders SCENE at SPP on one thread three ways, ROUNDS times each,
//! alternating, and prints the median seconds of each:
//! - `render`: the kernel as one machine runs it, each vertex traced and
//!   shaded in turn;
//! - `shading alone`: the same kernel over a tracer that answers every
//!   query from a recording of the render's answers, in order, without
//!   touching the BVH (the paths, and so the shading, are the same);
//! - `tracing alone`: the recorded queries traced back to back, with
//!   nothing between them.
//!
//! If the render takes longer than the other two together, the
//! difference is what interleaving costs (caches, branch predictors): what
//! a wavefront, which runs each kernel over a batch, could win back.
//!
//!     cargo run --release -p locus --example split_probe -- scenes/cornell-box/cornell.toml 8 5
use locus_core::geometry::Ray;
use locus_core::path::{RayKind, Traced, Tracer, WholeScene};
use locus_core::region::Resume;
use locus_core::render::Prepared;
use locus_core::scene::Scene;
use locus_core::stats::TraceStats;
use std::cell::{Cell, RefCell};
use std::hint::black_box;
use std::time::Instant;

/// The kinds of query a path makes, as the probe reports them.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Kind {
    Camera,
    Continuation,
    Shadow,
}

impl Kind {
    const ALL: [Kind; 3] = [Kind::Camera, Kind::Continuation, Kind::Shadow];

    fn name(self) -> &'static str {
        match self {
            Kind::Camera => "camera",
            Kind::Continuation => "continuation",
            Kind::Shadow => "shadow",
        }
    }
}

#[derive(Clone, Copy)]
struct Query {
    ray: Ray,
    t0: f32,
    t1: f32,
    kind: Kind,
}

/// One machine's tracer, writing down every query and its answer.
struct Recording<'a> {
    inner: WholeScene<'a>,
    queries: RefCell<Vec<Query>>,
    answers: RefCell<Vec<Traced>>,
}

impl Tracer for Recording<'_> {
    const FINISHES_ALL: bool = true;
    fn trace(
        &self,
        ray: &Ray,
        t_max: f32,
        resume: Resume,
        any: bool,
        kind: RayKind,
        st: &mut TraceStats,
    ) -> Traced {
        let t = self.inner.trace(ray, t_max, resume, any, kind, st);
        self.queries.borrow_mut().push(Query {
            ray: *ray,
            t0: resume.at.max(0.0),
            t1: t_max,
            kind: match (any, kind) {
                (true, _) => Kind::Shadow,
                (false, RayKind::Camera) => Kind::Camera,
                (false, RayKind::Secondary) => Kind::Continuation,
            },
        });
        self.answers.borrow_mut().push(t);
        t
    }
}

/// A tracer that answers from the recording, in order.
struct Replay<'a> {
    answers: &'a [Traced],
    next: Cell<usize>,
}

impl Tracer for Replay<'_> {
    const FINISHES_ALL: bool = true;
    #[inline]
    fn trace(
        &self,
        _ray: &Ray,
        _t_max: f32,
        _resume: Resume,
        _any: bool,
        _kind: RayKind,
        _st: &mut TraceStats,
    ) -> Traced {
        let i = self.next.get();
        self.next.set(i + 1);
        self.answers[i]
    }
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    anyhow::ensure!(a.len() >= 3, "usage: split_probe SCENE SPP [ROUNDS]");
    let scene = Scene::load(std::path::Path::new(&a[1]))?;
    let spp: u32 = a[2].parse()?;
    let rounds: usize = a.get(3).map_or(Ok(5), |r| r.parse())?;
    let prep = Prepared::new(scene);
    let kernel = prep.kernel(prep.scene.settings.max_depth, None);
    let (w, h) = (prep.scene.camera.width, prep.scene.camera.height);
    let render = |tracer: &dyn Fn(u32, u32, u32, &mut Vec<_>, &mut TraceStats) -> glam::Vec3| {
        let mut chain = Vec::new();
        let mut st = TraceStats::default();
        let mut sum = glam::Vec3::ZERO;
        for y in 0..h {
            for x in 0..w {
                for i in 0..spp {
                    sum += tracer(x, y, i, &mut chain, &mut st);
                }
            }
        }
        sum
    };
    let rec = Recording {
        inner: WholeScene(&prep.accel),
        queries: RefCell::new(Vec::new()),
        answers: RefCell::new(Vec::new()),
    };
    let want = render(&|x, y, i, c, st| kernel.sample(&rec, x, y, i, c, st));
    let queries = rec.queries.into_inner();
    let answers = rec.answers.into_inner();
    println!(
        "{} queries ({} shadow) over {} samples",
        queries.len(),
        queries.iter().filter(|q| q.kind == Kind::Shadow).count(),
        w as u64 * h as u64 * spp as u64
    );
    if let Ok(dir) = std::env::var("SPLIT_PROBE_DUMP") {
        dump(&prep, &queries, std::path::Path::new(&dir))?;
    }
    let whole = WholeScene(&prep.accel);
    let (mut t_render, mut t_shade, mut t_trace) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..rounds {
        let t = Instant::now();
        let got = render(&|x, y, i, c, st| kernel.sample(&whole, x, y, i, c, st));
        t_render.push(t.elapsed().as_secs_f64());
        assert_eq!(got, want);

        let replay = Replay {
            answers: &answers,
            next: Cell::new(0),
        };
        let t = Instant::now();
        let got = render(&|x, y, i, c, st| kernel.sample(&replay, x, y, i, c, st));
        t_shade.push(t.elapsed().as_secs_f64());
        assert_eq!(got, want, "the replayed paths are the render's");

        t_trace.push(trace_all(&prep, &queries).0);
    }
    // Each kind of query alone, and the shadow segments again with their
    // ends pulled back off the light: by three paddings (2^-18 of the
    // scene's magnitude, as the BVH pads a triangle's box), and by 0.1% and
    // 1% of their length (Mitsuba 3 stops its own 0.1% short).
    let samples = w as f64 * h as f64 * spp as f64;
    let pad = prep.scene.magnitude() * locus_core::geometry::SPAWN_OFFSET_REL;
    for kind in Kind::ALL {
        let picked: Vec<Query> = queries.iter().copied().filter(|q| q.kind == kind).collect();
        report(&prep, kind.name(), &picked, rounds, samples);
    }
    for (name, keep, back) in [
        ("shadow, 3 paddings short", 1.0, 3.0),
        ("shadow, 0.1% short", 0.999, 0.0),
        ("shadow, 1% short", 0.99, 0.0),
    ] {
        let picked: Vec<Query> = queries
            .iter()
            .filter(|q| q.kind == Kind::Shadow)
            .map(|&q| Query {
                t1: q.t1 * keep - back * pad,
                ..q
            })
            .collect();
        report(&prep, name, &picked, rounds, samples);
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (r, s, t) = (
        median(&mut t_render),
        median(&mut t_shade),
        median(&mut t_trace),
    );
    println!("render {r:.3} s, shading alone {s:.3} s, tracing alone {t:.3} s");
    println!(
        "render over the two apart: {:.3} (the two apart {:.3} s)",
        r / (s + t),
        s + t
    );
    Ok(())
}

/// Prints the median time of `rounds` passes over `picked`, a query and a
/// camera sample, with the BVH's counts a query and, in a small scene, the
/// triangles whose padded box (2^-18 of the scene's magnitude, as the BVH
/// pads them) each segment crosses: what an exact box a triangle would
/// leave to test.
fn report(prep: &Prepared, name: &str, picked: &[Query], rounds: usize, samples: f64) {
    let mut st = TraceStats::default();
    let mut times: Vec<f64> = (0..rounds)
        .map(|_| {
            let (t, s) = trace_all(prep, picked);
            st = s;
            t
        })
        .collect();
    times.sort_by(f64::total_cmp);
    let m = times[times.len() / 2];
    let n = picked.len() as f64;
    let exact = (prep.scene.tris.len() <= 4096).then(|| {
        let pad = prep.scene.magnitude() * locus_core::geometry::SPAWN_OFFSET_REL;
        let crossed = picked
            .iter()
            .map(|q| {
                prep.scene
                    .tris
                    .iter()
                    .filter(|t| crosses(t, pad, q))
                    .count()
            })
            .sum::<usize>();
        format!(", {:.2} triangle boxes crossed", crossed as f64 / n)
    });
    println!(
        "{name}: {} queries, {:.1} ns each, {:.3} µs a sample; {:.2} nodes and {:.2} triangle tests a query{}",
        picked.len(),
        m * 1e9 / n,
        m * 1e6 / samples,
        st.bvh_nodes as f64 / n,
        st.tri_tests as f64 / n,
        exact.unwrap_or_default(),
    );
}

/// Seconds to trace `queries` one after another, each as the render did
/// (a closest hit with its surface, or a shadow segment), and the BVH's
/// counts.
fn trace_all(prep: &Prepared, queries: &[Query]) -> (f64, TraceStats) {
    let mut st = TraceStats::default();
    let t = Instant::now();
    let mut hits = 0u64;
    for q in queries {
        if q.kind == Kind::Shadow {
            hits += prep.accel.occluded(&q.ray, q.t0, q.t1, &mut st) as u64;
        } else {
            hits += prep
                .accel
                .closest(&q.ray, q.t0, q.t1, &mut st)
                .map(|h| prep.accel.surface(&h))
                .is_some() as u64;
        }
    }
    black_box(hits);
    (t.elapsed().as_secs_f64(), st)
}

/// With `SPLIT_PROBE_DUMP=DIR`: the scene's triangles (`tris.f32`, nine
/// floats each) and each kind's queries (`camera.f32`, `continuation.f32`,
/// `shadow.f32`: origin, direction, start and end, eight floats each), for
/// tracing the render's own rays with another tracer.
fn dump(prep: &Prepared, queries: &[Query], dir: &std::path::Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    let floats = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let tris: Vec<f32> = prep
        .scene
        .tris
        .iter()
        .flat_map(|t| t.iter().flat_map(|v| v.to_array()))
        .collect();
    std::fs::write(dir.join("tris.f32"), floats(&tris))?;
    for kind in Kind::ALL {
        let v: Vec<f32> = queries
            .iter()
            .filter(|q| q.kind == kind)
            .flat_map(|q| {
                let (o, d) = (q.ray.origin, q.ray.dir);
                [o.x, o.y, o.z, d.x, d.y, d.z, q.t0, q.t1]
            })
            .collect();
        std::fs::write(dir.join(format!("{}.f32", kind.name())), floats(&v))?;
    }
    Ok(())
}

/// Whether the segment of `q` crosses triangle `t`'s box grown by `pad`
/// (a slab test in f64).
fn crosses(t: &[glam::Vec3; 3], pad: f32, q: &Query) -> bool {
    let lo = t[0].min(t[1]).min(t[2]).as_dvec3() - f64::from(pad);
    let hi = t[0].max(t[1]).max(t[2]).as_dvec3() + f64::from(pad);
    let (o, d) = (q.ray.origin.as_dvec3(), q.ray.dir.as_dvec3());
    let (mut a, mut b) = (f64::from(q.t0), f64::from(q.t1).min(1e30));
    for k in 0..3 {
        if d[k] == 0.0 {
            if o[k] < lo[k] || o[k] > hi[k] {
                return false;
            }
            continue;
        }
        let (t1, t2) = ((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]);
        a = a.max(t1.min(t2));
        b = b.min(t1.max(t2));
    }
    a <= b
}
