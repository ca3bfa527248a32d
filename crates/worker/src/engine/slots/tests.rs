//! Slots without sockets: tiles held and started, answers in any order,
//! chains that cascade, and spread passes.

use super::*;
use locus_core::geometry::Ray;
use locus_core::integrator::ShadowRay;
use locus_core::passes::Moments;
use locus_protocol::control::PassSamples;

/// Tile `tile` of `w` by `h` pixels, samples 2 and 3 of 4.
fn tile(tile: u32, w: u32, h: u32) -> TileAssignment {
    TileAssignment {
        job: 9,
        tile,
        pass: 2,
        samples: PassSamples::Even([2, 4]),
        x0: 10,
        y0: 20,
        x1: 10 + w,
        y1: 20 + h,
        queue_share: 0,
    }
}

fn vertex(e: f32) -> ShadedVertex {
    ShadedVertex {
        emitted: Vec3::splat(e),
        nee: Vec3::splat(1.0),
        scale: Vec3::splat(0.5),
    }
}

fn shadow() -> Query {
    Query::Shadow(ShadowRay {
        ray: Ray::new(Vec3::ZERO, Vec3::X),
        t_max: 1.0,
    })
}

/// Width, height and samples per pixel of the tests' image.
const IMAGE: [u32; 3] = [64, 64, 4];

#[test]
fn tiles_outside_the_image_are_refused() {
    let mut s = Slots::new(0, 9, IMAGE);
    for t in [
        tile(0, 60, 1),
        TileAssignment {
            samples: PassSamples::Even([2, 5]),
            ..tile(0, 1, 1)
        },
        TileAssignment {
            samples: PassSamples::Even([3, 3]),
            ..tile(0, 1, 1)
        },
    ] {
        assert!(s.add_tile(t).unwrap_err().contains("tile 0"));
    }
    assert!(s.start_sample().is_none());
}

#[test]
fn a_tile_goes_whole_only_before_its_first_sample() {
    let mut s = Slots::new(0, 9, IMAGE);
    s.add_tile(tile(1, 2, 1)).unwrap();
    s.add_tile(tile(2, 1, 1)).unwrap();
    assert!(!s.front_started() && s.whole_ready());
    let first = s.start_sample().unwrap();
    // Tile 1 has started: its other samples go one by one.
    assert!(s.front_started() && !s.whole_ready());
    assert_eq!(s.take_whole(), None);
    let rest: Vec<_> = (0..3).map_while(|_| s.start_sample()).collect();
    assert_eq!(rest.len(), 3);
    assert_eq!(s.samples_open(), 4);
    // Tile 2 has not: it goes whole, no slot opens for it, and it stays
    // held until it is done.
    assert!(!s.front_started() && s.whole_ready());
    assert_eq!(s.take_whole(), Some(tile(2, 1, 1)));
    assert!(!s.whole_ready());
    assert_eq!((s.take_whole(), s.start_sample()), (None, None));
    assert_eq!((s.tiles_held().0, s.pending()), (2, 4));
    s.whole_done();
    assert_eq!(s.tiles_held().0, 1);
    // Tile 1 still finishes sample by sample.
    let (mut fx, mut st) = (Vec::new(), TraceStats::default());
    for n in std::iter::once(first).chain(rest) {
        let l = Answer::Radiance(Vec3::ONE);
        s.answer(0, n.reply.slot, l, &mut fx, &mut st).unwrap();
    }
    assert!(matches!(&fx[..], [Effect::TileDone(r)] if r.tile == 1 && r.sums.len() == 2));
    assert_eq!(s.tiles_held().0, 0);
}

#[test]
fn a_slot_fits_a_cache_line() {
    assert_eq!(std::mem::size_of::<Slot>(), 64);
}

#[test]
fn samples_fill_tiles_in_index_order() {
    let mut s = Slots::new(0, 9, IMAGE);
    s.add_tile(tile(4, 2, 1)).unwrap();
    let mut started = Vec::new();
    while let Some(n) = s.start_sample() {
        started.push(n);
    }
    let xs: Vec<(u32, u32, u32)> = started.iter().map(|n| (n.x, n.y, n.sample)).collect();
    assert_eq!(xs, [(10, 20, 2), (10, 20, 3), (11, 20, 2), (11, 20, 3)]);
    assert_eq!(s.samples_open(), 4);
    let mut fx = Vec::new();
    let mut st = TraceStats::default();
    // Answers in any order; the pixel sums do not depend on it.
    for (k, n) in started.iter().enumerate().rev() {
        let v = if k == 3 { f32::NAN } else { k as f32 };
        s.answer(
            0,
            n.reply.slot,
            Answer::Radiance(Vec3::splat(v)),
            &mut fx,
            &mut st,
        )
        .unwrap();
    }
    assert_eq!(s.samples_open(), 0);
    assert_eq!(s.pending(), 0);
    let Effect::TileDone(t) = &fx[0] else {
        panic!("{fx:?}")
    };
    assert_eq!((t.tile, t.pass), (4, 2));
    // Samples 0 and 1, then 2 and NaN (dropped): sums and squares.
    let m = |sum: f64, squares: f64| Moments {
        sum: [sum; 3],
        squares: [squares; 3],
    };
    assert_eq!(t.sums, vec![m(1.0, 1.0), m(2.0, 4.0)]);
    assert_eq!((st.samples, st.invalid_samples), (4, 1));
}

#[test]
fn a_spread_pass_starts_each_pixels_own_samples() {
    let mut s = Slots::new(0, 9, IMAGE);
    // Three pixels: 2 samples from 5, none, 1 from 9 (past the 4 spp:
    // a spread pixel may take up to MAX_SHARE times it).
    let spread = TileAssignment {
        samples: PassSamples::Spread {
            first: vec![5, 7, 9],
            count: vec![2, 0, 1],
        },
        ..tile(6, 3, 1)
    };
    assert_eq!(s.add_tile(spread.clone()), Ok(None));
    let started: Vec<NewSample> = std::iter::from_fn(|| s.start_sample()).collect();
    let xs: Vec<(u32, u32, u32)> = started.iter().map(|n| (n.x, n.y, n.sample)).collect();
    assert_eq!(xs, [(10, 20, 5), (10, 20, 6), (12, 20, 9)]);
    let (mut fx, mut st) = (Vec::new(), TraceStats::default());
    for (k, n) in started.iter().enumerate() {
        let l = Answer::Radiance(Vec3::splat(k as f32 + 1.0));
        s.answer(0, n.reply.slot, l, &mut fx, &mut st).unwrap();
    }
    let Effect::TileDone(t) = &fx[0] else {
        panic!("{fx:?}")
    };
    let m = |sum: f64, squares: f64| Moments {
        sum: [sum; 3],
        squares: [squares; 3],
    };
    assert_eq!(t.sums, vec![m(3.0, 5.0), m(0.0, 0.0), m(3.0, 9.0)]);
    assert_eq!(s.tiles_held().0, 0);
    // A pass that gives the tile no samples is done when it arrives.
    let none = TileAssignment {
        samples: PassSamples::Spread {
            first: vec![5, 7, 9],
            count: vec![0; 3],
        },
        ..spread
    };
    let done = s.add_tile(none).unwrap().expect("done at once");
    assert_eq!((done.tile, done.sums), (6, vec![Moments::default(); 3]));
    assert_eq!((s.tiles_held().0, s.start_sample()), (0, None));
}

#[test]
fn chains_cascade_and_reply_once() {
    let mut s = Slots::new(1, 9, IMAGE);
    s.add_tile(TileAssignment {
        pass: 3,
        samples: PassSamples::Even([3, 4]),
        ..tile(0, 1, 1)
    })
    .unwrap();
    let n = s.start_sample().unwrap();
    // Vertex 0: shadow forwarded, continuation is vertex 1; vertex 1:
    // shadow done, continuation forwarded with a cache entry to update.
    let chain = [
        ChainVertex {
            vertex: vertex(1.0),
            shadow: Child::Forward(Dest::Peer(2), shadow(), Resume::at(0.5)),
            next: Child::Deeper,
            update: None,
        },
        ChainVertex {
            vertex: vertex(2.0),
            shadow: Child::Done(false),
            next: Child::Forward(Dest::Peer(0), shadow(), Resume::at(0.25)),
            update: Some((7, Vec3::Y)),
        },
    ];
    let mut out = Vec::new();
    s.open_chain(n.reply, &chain, &mut out);
    assert_eq!(out.len(), 2);
    assert_eq!(s.pending(), 3);
    let (mut fx, mut st) = (Vec::new(), TraceStats::default());
    // Vertex 1's continuation: L1 = (2 + 0) + 0.5 * 4 = 4; vertex 0
    // still waits for its shadow.
    s.answer(
        0,
        out[1].3.slot,
        Answer::Radiance(Vec3::splat(4.0)),
        &mut fx,
        &mut st,
    )
    .unwrap();
    assert_eq!(
        fx,
        vec![Effect::CacheUpdate((7, Vec3::Y), Vec3::splat(4.0))]
    );
    // The same slot again is refused: it is free now.
    assert!(
        s.answer(
            0,
            out[1].3.slot,
            Answer::Radiance(Vec3::ONE),
            &mut fx,
            &mut st
        )
        .is_err()
    );
    fx.clear();
    // Shadow of vertex 0 visible: L0 = (1 + 1) + 0.5 * 4 = 4, and the
    // sample (a tile of one pixel) is done.
    s.answer(2, out[0].3.slot, Answer::Visible(true), &mut fx, &mut st)
        .unwrap();
    let Effect::TileDone(t) = &fx[0] else {
        panic!("{fx:?}")
    };
    assert_eq!(
        t.sums,
        vec![Moments {
            sum: [4.0; 3],
            squares: [16.0; 3]
        }]
    );
    assert_eq!(s.pending(), 0);
}

#[test]
fn a_vertex_asked_by_another_worker_replies_there() {
    let mut s = Slots::new(1, 9, IMAGE);
    let asker = ReplyTo {
        worker: 3,
        slot: 77,
    };
    let chain = [ChainVertex {
        vertex: vertex(0.0),
        shadow: Child::Done(true),
        next: Child::Forward(Dest::Peer(0), shadow(), Resume::at(0.0)),
        update: None,
    }];
    let mut out = Vec::new();
    s.open_chain(asker, &chain, &mut out);
    let (mut fx, mut st) = (Vec::new(), TraceStats::default());
    // A wrong kind of answer is refused.
    assert!(
        s.answer(0, out[0].3.slot, Answer::Visible(true), &mut fx, &mut st)
            .is_err()
    );
    s.answer(
        0,
        out[0].3.slot,
        Answer::Radiance(Vec3::ONE),
        &mut fx,
        &mut st,
    )
    .unwrap();
    assert_eq!(
        fx,
        vec![Effect::Reply(asker, Answer::Radiance(Vec3::splat(1.5)))]
    );
    assert!(
        s.answer(0, 12345, Answer::Visible(true), &mut fx, &mut st)
            .is_err()
    );
}

/// A continuation that went on as a segment query: a hit inside the
/// sphere answers the vertex and updates no cache; a segment that got
/// beyond asks for the cache (or the rest of the ray), whose radiance
/// then updates the cache. A second `Beyond`, or one for a vertex with
/// no segment out, is refused.
#[test]
fn segments_answer_inside_or_hand_back_beyond() {
    let ray = PathRay::camera(
        Ray::new(Vec3::ZERO, Vec3::X),
        locus_core::sampler::SampleKey::independent(5, 1, 2),
    );
    let key = (42, Vec3::X);
    let asker = ReplyTo {
        worker: 3,
        slot: 77,
    };
    let chain = [ChainVertex {
        vertex: vertex(0.0),
        shadow: Child::Done(true),
        next: Child::Forward(Dest::Peer(0), Query::Segment(ray), Resume::at(0.0)),
        update: Some(key),
    }];
    let (mut fx, mut st) = (Vec::new(), TraceStats::default());
    // Inside: the radiance finishes the vertex, and no cache hears of it.
    let mut s = Slots::new(1, 9, IMAGE);
    let mut out = Vec::new();
    s.open_chain(asker, &chain, &mut out);
    let slot = out[0].3.slot;
    s.answer(0, slot, Answer::Radiance(Vec3::ONE), &mut fx, &mut st)
        .unwrap();
    assert_eq!(
        fx,
        vec![Effect::Reply(asker, Answer::Radiance(Vec3::splat(1.5)))]
    );
    // Beyond: the engine is asked to finish it; its radiance then
    // updates the cache.
    fx.clear();
    let mut out = Vec::new();
    s.open_chain(asker, &chain, &mut out);
    let slot = out[0].3.slot;
    s.answer(0, slot, Answer::Beyond, &mut fx, &mut st).unwrap();
    assert_eq!(fx, vec![Effect::Beyond { slot, key, ray }]);
    assert!(s.answer(0, slot, Answer::Beyond, &mut fx, &mut st).is_err());
    fx.clear();
    s.expect_update(slot, key);
    s.answer(1, slot, Answer::Radiance(Vec3::ONE), &mut fx, &mut st)
        .unwrap();
    assert_eq!(
        fx,
        vec![
            Effect::CacheUpdate(key, Vec3::ONE),
            Effect::Reply(asker, Answer::Radiance(Vec3::splat(1.5)))
        ]
    );
    // A vertex whose continuation is no segment takes no `Beyond`.
    let plain = [ChainVertex {
        next: Child::Forward(Dest::Peer(0), shadow(), Resume::at(0.0)),
        update: None,
        ..chain[0]
    }];
    let mut out = Vec::new();
    s.open_chain(asker, &plain, &mut out);
    assert!(
        s.answer(0, out[0].3.slot, Answer::Beyond, &mut fx, &mut st)
            .is_err()
    );
}
