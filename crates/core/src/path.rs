//! The path state machine: how every path vertex is evaluated, once, for
//! the single machine and the farm alike (pbrt-v4's CPU and wavefront
//! integrators share their per-vertex code the same way).
//!
//! A work item is a camera sample or a [`Query`]: a path ray ("the radiance
//! arriving along it"), a shadow segment ("is it unoccluded"), or, with
//! directional caches on the farm, the part of a continuation ray inside its
//! locality sphere ("the radiance, if it hits before the perimeter"). The
//! [`Kernel`] traces it through a [`Tracer`], which either finishes the
//! segment (a hit, a miss, an occluder) or says where it must go on
//! ([`Traced::Next`]). A hit is shaded ([`crate::integrator::shade`]); its
//! shadow segment and its continuation are traced the same way,
//! depth-first, and with directional caches on the continuation is traced
//! exactly inside its leaf's locality sphere and answered by the leaf's
//! cache beyond it when the cache can. Everything that stays with the
//! tracer is finished in one call; a vertex that waits for a child that
//! must go elsewhere is left in a chain of [`ChainVertex`]es, each the
//! continuation of the one before, which the farm keeps in pending slots
//! until the answers come back and then finishes with the very same
//! [`ShadedVertex::finish`].
//!
//! The single machine's tracer ([`WholeScene`]) never says `Next`, so every
//! item finishes at once; that is the only difference between one machine
//! and a farm worker, and why their images agree bit for bit by
//! construction. [`crate::passes`] has the one pixel mean both use.

use crate::accel::{Accel, Surface};
use crate::accel_set::AccelSet;
use crate::dircache::LeafCaches;
use crate::geometry::Ray;
use crate::integrator::{DIM_PIXEL, PathRay, ShadedVertex, ShadowRay, shade};
use crate::irradiance::IrradianceCache;
use crate::light::LightSet;
use crate::octree::Octree;
use crate::region::{Resume, WorkerId};
use crate::sampler::{SampleKey, Sampler};
use crate::scene::{Camera, CameraView, Material};
use crate::stats::TraceStats;
use glam::Vec3;
use serde::{Deserialize, Serialize};

/// A question about one ray that any worker holding the right geometry
/// can answer.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Query {
    /// Radiance arriving along the ray (see [`PathRay`]).
    Path(PathRay),
    /// Whether the segment is unoccluded.
    Shadow(ShadowRay),
    /// A continuation ray inside its locality sphere only (directional
    /// caches on): the radiance arriving along it if it hits a surface
    /// before the perimeter (`emit_within`), otherwise [`Answer::Beyond`],
    /// and its origin's leaf cache answers for the rest or traces on. So a
    /// ray that leaves its worker's region inside the sphere still reaches
    /// the cache, and no owner beyond the perimeter sees it.
    Segment(PathRay),
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Answer {
    Radiance(Vec3),
    Visible(bool),
    /// A [`Query::Segment`] reached its perimeter without a hit.
    Beyond,
}

/// Where a query goes on when this tracer cannot finish it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dest {
    /// To the owner of the next leaf along the ray.
    Peer(WorkerId),
    /// Back here once that leaf's geometry has arrived (demand-driven).
    Leaf(u32),
}

/// What tracing one segment found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Traced {
    Hit(Surface),
    Occluded,
    Miss,
    /// Go on elsewhere, from where the resume says.
    Next(Dest, Resume),
}

/// What a ray is, for policies that treat camera rays apart.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RayKind {
    Camera,
    Secondary,
}

/// Traces segments through the geometry at hand.
pub trait Tracer {
    /// Whether every segment finishes here (no `trace` says
    /// [`Traced::Next`]): no vertex then waits, and the kernel keeps no
    /// chain of them (one machine).
    const FINISHES_ALL: bool = false;

    /// The closest hit of `ray` on `[0, t_max)` from `resume.at` (with
    /// `any`: whether anything blocks it), or where it must go on.
    fn trace(
        &self,
        ray: &Ray,
        t_max: f32,
        resume: Resume,
        any: bool,
        kind: RayKind,
        stats: &mut TraceStats,
    ) -> Traced;
}

/// Geometry that holds every triangle of the scene: one BVH, or a farm
/// worker's parts when the scene is replicated to it.
pub trait WholeGeometry {
    fn closest_surface(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> Option<Surface>;
    fn occluded(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> bool;
}

impl WholeGeometry for Accel {
    #[inline]
    fn closest_surface(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> Option<Surface> {
        self.closest(ray, t0, t1, st).map(|h| self.surface(&h))
    }
    #[inline]
    fn occluded(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> bool {
        Accel::occluded(self, ray, t0, t1, st)
    }
}

impl WholeGeometry for AccelSet {
    #[inline]
    fn closest_surface(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> Option<Surface> {
        self.closest(ray, t0, t1, st).map(|h| self.surface(&h))
    }
    #[inline]
    fn occluded(&self, ray: &Ray, t0: f32, t1: f32, st: &mut TraceStats) -> bool {
        AccelSet::occluded(self, ray, t0, t1, st)
    }
}

/// The tracer of one machine: geometry holding the whole scene (a BVH
/// over it, or a replicated worker's parts), so every segment finishes.
pub struct WholeScene<'a, G: WholeGeometry = Accel>(pub &'a G);

impl<G: WholeGeometry> Tracer for WholeScene<'_, G> {
    const FINISHES_ALL: bool = true;

    #[inline]
    fn trace(
        &self,
        ray: &Ray,
        t_max: f32,
        resume: Resume,
        any: bool,
        _kind: RayKind,
        stats: &mut TraceStats,
    ) -> Traced {
        let t0 = resume.at.max(0.0);
        if any {
            if self.0.occluded(ray, t0, t_max, stats) {
                Traced::Occluded
            } else {
                Traced::Miss
            }
        } else {
            match self.0.closest_surface(ray, t0, t_max, stats) {
                Some(s) => Traced::Hit(s),
                None => Traced::Miss,
            }
        }
    }
}

/// The directional caches and the octree whose leaves they belong to.
#[derive(Clone, Copy)]
pub struct CacheUse<'a> {
    pub octree: &'a Octree,
    pub caches: &'a LeafCaches,
}

/// A directional cache entry to update when a continuation's radiance is
/// known: the leaf and the ray's direction.
pub type CacheKey = (u32, Vec3);

/// What a work item is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Task {
    Query(Query),
    /// A camera sample, whose ray is made where it is traced.
    Camera {
        x: u32,
        y: u32,
        sample: u32,
    },
}

/// A child query of a vertex.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Child<T> {
    Done(T),
    /// Must go on elsewhere, resuming as given.
    Forward(Dest, Query, Resume),
    /// The next vertex of the chain.
    Deeper,
}

/// A vertex shaded here whose shadow answer or continuation is pending.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChainVertex {
    pub vertex: ShadedVertex,
    pub shadow: Child<bool>,
    pub next: Child<Vec3>,
    /// The cache entry the continuation's radiance updates when it comes;
    /// for a continuation that went on as a [`Query::Segment`], the cache
    /// that answers if the segment gets beyond its perimeter.
    pub update: Option<CacheKey>,
}

/// How a work item ended here.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Outcome {
    Answer(Answer),
    /// The query goes on elsewhere, resuming as `resume` says.
    Forward {
        dest: Dest,
        query: Query,
        resume: Resume,
    },
    /// Vertices `start..end` of the caller's chain wait on forwarded
    /// children; vertex k+1 is the continuation of vertex k.
    Chain {
        start: u32,
        end: u32,
    },
}

/// Everything that evaluating a vertex needs besides the geometry.
#[derive(Clone, Copy)]
pub struct Kernel<'a> {
    pub materials: &'a [Material],
    pub lights: &'a LightSet,
    pub camera: &'a Camera,
    /// The camera's frame, computed once (see [`Camera::view`]).
    pub view: CameraView,
    pub seed: u64,
    pub sampler: Sampler,
    pub max_depth: u32,
    /// Directional caches per octree leaf; None traces every ray.
    pub cache: Option<CacheUse<'a>>,
    /// Ward's irradiance cache for the first vertex's interreflection
    /// (read only while rendering); None path traces it.
    pub irradiance: Option<&'a IrradianceCache>,
}

impl<'a> Kernel<'a> {
    /// A kernel that traces every ray: no directional or irradiance cache.
    pub fn exact(
        materials: &'a [Material],
        lights: &'a LightSet,
        camera: &'a Camera,
        seed: u64,
        sampler: Sampler,
        max_depth: u32,
    ) -> Self {
        Self {
            materials,
            lights,
            camera,
            view: camera.view(),
            seed,
            sampler,
            max_depth,
            cache: None,
            irradiance: None,
        }
    }

    /// This kernel without its caches: what the irradiance overture
    /// measures with, wherever it runs.
    pub fn without_caches(&self) -> Self {
        Self {
            cache: None,
            irradiance: None,
            ..*self
        }
    }
}

impl Kernel<'_> {
    /// The key of a camera sample.
    #[inline]
    pub fn sample_key(&self, x: u32, y: u32, sample: u32) -> SampleKey {
        SampleKey::new(
            y as u64 * self.camera.width as u64 + x as u64,
            sample,
            self.seed,
            self.sampler,
        )
    }

    /// Evaluates one work item as far as `tracer` can take it. Vertices
    /// that wait on forwarded children are appended to `chain`.
    pub fn process<T: Tracer>(
        &self,
        tracer: &T,
        task: Task,
        resume: Resume,
        chain: &mut Vec<ChainVertex>,
        st: &mut TraceStats,
    ) -> Outcome {
        let query = match task {
            Task::Query(q) => q,
            Task::Camera { x, y, sample } => {
                let key = self.sample_key(x, y, sample);
                st.camera_rays += 1;
                let ray = self.view.ray(x, y, key.get2d(DIM_PIXEL));
                Query::Path(PathRay::camera(ray, key))
            }
        };
        match query {
            Query::Shadow(s) => {
                match tracer.trace(&s.ray, s.t_max, resume, true, RayKind::Secondary, st) {
                    Traced::Next(dest, t) => Outcome::Forward {
                        dest,
                        query,
                        resume: t,
                    },
                    Traced::Miss => Outcome::Answer(Answer::Visible(true)),
                    Traced::Occluded | Traced::Hit(_) => Outcome::Answer(Answer::Visible(false)),
                }
            }
            Query::Path(q) | Query::Segment(q) => {
                // A segment stops at its perimeter and says so when it gets
                // there; a path goes on to infinity.
                let segment = matches!(query, Query::Segment(_));
                let (t_max, kind, miss) = if segment {
                    (q.emit_within, RayKind::Secondary, Answer::Beyond)
                } else if q.depth == 0 {
                    (f32::INFINITY, RayKind::Camera, Answer::Radiance(Vec3::ZERO))
                } else {
                    (
                        f32::INFINITY,
                        RayKind::Secondary,
                        Answer::Radiance(Vec3::ZERO),
                    )
                };
                match tracer.trace(&q.ray, t_max, resume, false, kind, st) {
                    Traced::Next(dest, t) => Outcome::Forward {
                        dest,
                        query,
                        resume: t,
                    },
                    Traced::Miss | Traced::Occluded => Outcome::Answer(miss),
                    Traced::Hit(h) => {
                        if segment {
                            st.cache.local += 1;
                        }
                        let start = chain.len();
                        match self.eval_hit(tracer, &q, &h, chain, st) {
                            Some(l) => Outcome::Answer(Answer::Radiance(l)),
                            None => Outcome::Chain {
                                start: start as u32,
                                end: chain.len() as u32,
                            },
                        }
                    }
                }
            }
        }
    }

    /// The radiance of one camera sample on a tracer that finishes every
    /// segment (one machine).
    pub fn sample<T: Tracer>(
        &self,
        tracer: &T,
        x: u32,
        y: u32,
        sample: u32,
        chain: &mut Vec<ChainVertex>,
        st: &mut TraceStats,
    ) -> Vec3 {
        let task = Task::Camera { x, y, sample };
        match self.process(tracer, task, Resume::START, chain, st) {
            Outcome::Answer(Answer::Radiance(l)) => l,
            other => unreachable!("a tracer that never forwards left {other:?}"),
        }
    }

    /// The radiance arriving along `q` and the distance to the surface it
    /// hits first (infinite if none), on a tracer that finishes every
    /// segment: what an irradiance record's rays measure.
    pub fn first_hit<T: Tracer>(
        &self,
        tracer: &T,
        q: &PathRay,
        chain: &mut Vec<ChainVertex>,
        st: &mut TraceStats,
    ) -> (Vec3, f32) {
        st.indirect_rays += 1;
        let t = tracer.trace(
            &q.ray,
            f32::INFINITY,
            Resume::START,
            false,
            RayKind::Secondary,
            st,
        );
        match t {
            Traced::Miss | Traced::Occluded => (Vec3::ZERO, f32::INFINITY),
            Traced::Hit(h) => match self.eval_hit(tracer, q, &h, chain, st) {
                Some(l) => (l, h.hit.t),
                None => unreachable!("a tracer that never forwards left a chain"),
            },
            Traced::Next(..) => unreachable!("a tracer that never forwards said Next"),
        }
    }

    /// Shades hit `h` of `q` and evaluates its shadow and continuation
    /// queries as far as they stay with the tracer. Returns the vertex's
    /// radiance when everything finished; otherwise leaves this vertex (and
    /// the pending ones below it) at the end of `chain` and returns None.
    fn eval_hit<T: Tracer>(
        &self,
        tracer: &T,
        q: &PathRay,
        h: &Surface,
        chain: &mut Vec<ChainVertex>,
        st: &mut TraceStats,
    ) -> Option<Vec3> {
        let mat = &self.materials[h.material as usize];
        let s = shade(
            q,
            &h.hit,
            &h.verts,
            h.shading,
            mat,
            self.lights,
            self.max_depth,
            self.cache.map(|c| (c.octree, c.caches.params.radius)),
            self.irradiance,
        );
        match s.ambient {
            Some(true) => st.irradiance.interpolated += 1,
            Some(false) => st.irradiance.traced += 1,
            None => {}
        }
        let shadow = match s.shadow {
            None => Child::Done(false),
            Some(sr) => {
                st.shadow_rays += 1;
                let ray = &sr.ray;
                match tracer.trace(ray, sr.t_max, Resume::START, true, RayKind::Secondary, st) {
                    Traced::Miss => Child::Done(true),
                    Traced::Occluded | Traced::Hit(_) => Child::Done(false),
                    Traced::Next(dest, t) => Child::Forward(dest, Query::Shadow(sr), t),
                }
            }
        };
        let next = |chain: &mut Vec<ChainVertex>, st: &mut TraceStats| match s.next {
            None => (Child::Done(Vec3::ZERO), None),
            Some(nq) => {
                st.indirect_rays += 1;
                self.continuation(tracer, &nq, s.cache_leaf, chain, st)
            }
        };
        if T::FINISHES_ALL {
            // Nothing waits: the vertex is finished without a place in the
            // chain, the same arithmetic in the same order (the Cornell box
            // at 2 spp, one thread: 1.7% fewer instructions, the image
            // bit-identical).
            return match (shadow, next(chain, st).0) {
                (Child::Done(visible), Child::Done(l)) => Some(s.vertex.finish(visible, l)),
                _ => unreachable!("a tracer that finishes every segment left one pending"),
            };
        }
        // The vertex takes its place in the chain only when something of it
        // waits: most vertices of a farm worker finish here, and writing
        // each into the chain and reading it back cost more than placing
        // the few that wait. Its continuation's own waiting vertices, if
        // any, were appended meanwhile; this one goes before them.
        let idx = chain.len();
        let (next, update) = next(chain, st);
        if let (Child::Done(visible), Child::Done(l)) = (&shadow, &next) {
            return Some(s.vertex.finish(*visible, *l));
        }
        let v = ChainVertex {
            vertex: s.vertex,
            shadow,
            next,
            update,
        };
        if idx == chain.len() {
            chain.push(v);
        } else {
            chain.insert(idx, v);
        }
        None
    }

    /// A continuation ray. Without caches it is traced like any query.
    /// With them it is traced exactly inside the locality sphere of the
    /// leaf it starts in (`leaf`, from [`shade`]); a ray that hits nothing
    /// there is answered by the leaf's cache when the cache can, and
    /// otherwise traced on; its radiance updates the cache at once when it
    /// is known here, or (the returned key) when its answer comes back.
    fn continuation<T: Tracer>(
        &self,
        tracer: &T,
        nq: &PathRay,
        leaf: Option<u32>,
        chain: &mut Vec<ChainVertex>,
        st: &mut TraceStats,
    ) -> (Child<Vec3>, Option<CacheKey>) {
        let follow = |t: Traced, chain: &mut Vec<ChainVertex>, st: &mut TraceStats| match t {
            Traced::Miss | Traced::Occluded => Child::Done(Vec3::ZERO),
            Traced::Next(dest, t) => Child::Forward(dest, Query::Path(*nq), t),
            Traced::Hit(h) => match self.eval_hit(tracer, nq, &h, chain, st) {
                Some(l) => Child::Done(l),
                None => Child::Deeper,
            },
        };
        let (Some(c), Some(leaf)) = (self.cache, leaf) else {
            let t = tracer.trace(
                &nq.ray,
                f32::INFINITY,
                Resume::START,
                false,
                RayKind::Secondary,
                st,
            );
            return (follow(t, chain, st), None);
        };
        // `shade` found the leaf and used the perimeter `emit_within` for
        // this ray's emission and its vertex's next-event weights.
        let tp = nq.emit_within;
        let inside = tracer.trace(&nq.ray, tp, Resume::START, false, RayKind::Secondary, st);
        match inside {
            Traced::Miss => {}
            // The sphere goes on in another worker's region: the rest of it
            // is a segment query, whose owner answers a hit or that the
            // ray got beyond (counted where that is known), and the key is
            // the cache that then answers here.
            Traced::Next(dest, t) => {
                st.cache.segments += 1;
                let seg = Child::Forward(dest, Query::Segment(*nq), t);
                return (seg, Some((leaf, nq.ray.dir)));
            }
            Traced::Hit(_) | Traced::Occluded => {
                st.cache.local += 1;
                return (follow(inside, chain, st), None);
            }
        }
        if let Some(v) = c.caches.at_perimeter(leaf, nq.ray.dir, &mut st.cache) {
            return (Child::Done(v), None);
        }
        let beyond = tracer.trace(
            &nq.ray,
            f32::INFINITY,
            Resume::at(tp),
            false,
            RayKind::Secondary,
            st,
        );
        match follow(beyond, chain, st) {
            Child::Done(v) => {
                c.caches.update(leaf, nq.ray.dir, v);
                (Child::Done(v), None)
            }
            pending => (pending, Some((leaf, nq.ray.dir))),
        }
    }
}
