//! The film against one machine's sums: passes in any order, kept
//! tiles, the noise target's barrier and adaptive sampling's spread.

use super::*;
use glam::Vec3;
use locus_core::passes::pixel_mean;
use locus_core::render::{TileOrder, tiles};
use locus_core::stats::TraceStats;

const W: u32 = 7;
const H: u32 = 5;
const SPP: u32 = 13;

fn film() -> Film {
    Film::new(W, H, SPP, tiles(W, H, 3, TileOrder::Scanline))
}

/// A sample whose sums are sensitive to the order they are added in,
/// noisier in the image's first three columns than in the others.
fn sample(x: u32, y: u32, s: u32) -> Vec3 {
    let v = ((x * 31 + y * 17 + s * 7) % 11) as f32;
    let v = if x < 3 { v } else { 5.0 + (v - 5.0) * 0.05 };
    Vec3::new(v * 1e7, 1.0 / (v + 0.3), (s as f32).sin() * 1e-3)
}

/// What a worker sends for unit `u`.
fn render(f: &Film, u: Unit) -> Vec<Moments> {
    let a = f.assignment(u, 3, 0);
    let mut st = TraceStats::default();
    let mut v = Vec::new();
    for y in a.y0..a.y1 {
        for x in a.x0..a.x1 {
            let mut p = PixelSum::default();
            for s in a.pixel_samples(v.len() as u32) {
                p.add(sample(x, y, s), &mut st);
            }
            v.push(p.total());
        }
    }
    v
}

fn one_machine() -> Vec<[f32; 3]> {
    one_machine_sums().iter().map(|p| p.mean(SPP)).collect()
}

/// The estimate as one machine makes it: from its image and its
/// variance image.
fn one_machine_estimate() -> ErrorEstimate {
    let sums = one_machine_sums();
    let mut variance = Image::new(W, H);
    variance.pixels = sums
        .iter()
        .map(|p| p.variance_of_mean_f32(SPP).unwrap())
        .collect();
    let mut image = Image::new(W, H);
    image.pixels = one_machine();
    locus_core::metrics::estimate_error(&image, &variance, SPP)
}

fn one_machine_sums() -> Vec<PixelSum> {
    let mut st = TraceStats::default();
    (0..H)
        .flat_map(|y| (0..W).map(move |x| (x, y)))
        .map(|(x, y)| pixel_mean(SPP, &mut st, |s, _| sample(x, y, s)))
        .collect()
}

#[test]
fn passes_in_any_order_give_one_machines_image() {
    let mut f = film();
    let mut units = f.missing();
    assert_eq!(units.len(), f.tiles().len() * f.passes().len());
    // Latest passes first, and every unit twice.
    units.reverse();
    for u in units.iter().chain(&units) {
        let s = render(&f, *u);
        let r = f.add(*u, s);
        assert!(r.is_ok() || r == Err(Refused::Duplicate), "{r:?}");
    }
    assert!(f.is_complete());
    assert!(f.missing().is_empty());
    assert_eq!(f.samples(), ((W * H * SPP) as u64, (W * H * SPP) as u64));
    assert_eq!(f.image().pixels, one_machine());
    // The squares add up in the same order: the same error estimate
    // to the bit.
    let one = one_machine_estimate();
    assert_eq!(f.error_estimate(), Some(one));
}

#[test]
fn a_kept_tile_comes_back_whole() {
    let mut f = film();
    let first: Vec<Unit> = f.missing().into_iter().filter(|u| u.pass < 2).collect();
    for u in &first {
        let s = render(&f, *u);
        f.add(*u, s).unwrap();
    }
    assert_eq!(f.pass(), 2);
    let mut again = film();
    for t in 0..f.tiles().len() as u32 {
        assert!(again.restore(t, f.tile_sums(t)));
        assert!(!again.restore(t, f.tile_sums(t)), "a tile restored twice");
    }
    assert_eq!(again.samples(), f.samples());
    assert_eq!(again.image().pixels, f.image().pixels);
    for u in again.missing() {
        let s = render(&again, u);
        again.add(u, s).unwrap();
    }
    assert_eq!(again.image().pixels, one_machine());
    assert_eq!(again.error_estimate(), Some(one_machine_estimate()));
}

#[test]
fn bad_results_are_refused() {
    let mut f = film();
    let u = Unit { tile: 0, pass: 0 };
    assert_eq!(
        f.add(Unit { tile: 99, pass: 0 }, vec![]),
        Err(Refused::Unknown)
    );
    assert_eq!(
        f.add(Unit { tile: 0, pass: 99 }, vec![]),
        Err(Refused::Unknown)
    );
    assert_eq!(
        f.add(u, vec![Moments::default(); 2]),
        Err(Refused::Size { got: 2, want: 9 })
    );
    let s = render(&f, u);
    assert_eq!(f.add(u, s.clone()), Ok(true));
    assert_eq!(f.add(u, s), Err(Refused::Duplicate));
    // A held early pass counts as in, once.
    let late = Unit { tile: 1, pass: 3 };
    let s = render(&f, late);
    assert_eq!(f.add(late, s.clone()), Ok(false));
    assert_eq!(f.add(late, s), Err(Refused::Duplicate));
    assert!(!f.restore(0, f.tile_sums(0)), "over a tile that has passes");
    assert!(!f.restore(
        2,
        TileSums {
            passes: 9,
            sums: vec![Moments::default(); 9],
            counts: vec![13; 9],
        }
    ));
    // Pass 0 of 13 spp is 2 samples a pixel: a count that says
    // otherwise does not fit.
    let one_pass = |counts: Vec<u32>| TileSums {
        passes: 1,
        sums: vec![Moments::default(); 9],
        counts,
    };
    let mut fresh = film();
    assert!(!fresh.restore(0, one_pass(vec![3; 9])));
    assert!(!fresh.restore(0, one_pass(vec![2; 8])));
    assert!(fresh.restore(0, one_pass(vec![2; 9])));
}

#[test]
fn the_preview_is_the_mean_of_the_passes_in() {
    let mut f = film();
    for u in f.missing().into_iter().filter(|u| u.pass == 0) {
        let s = render(&f, u);
        f.add(u, s).unwrap();
    }
    // Pass 0 of 13 spp is samples 0 and 1.
    assert_eq!(f.passes()[0], 0..2);
    let img = f.image();
    let mut st = TraceStats::default();
    for (i, p) in img.pixels.iter().enumerate() {
        let (x, y) = (i as u32 % W, i as u32 / W);
        let mut first = PixelSum::default();
        first.add(sample(x, y, 0), &mut st);
        first.add(sample(x, y, 1), &mut st);
        assert_eq!(*p, first.mean(2));
    }
    assert_eq!(f.pass(), 1);
    assert_eq!(
        f.units(),
        (
            f.tiles().len() as u64,
            (f.tiles().len() * f.passes().len()) as u64
        )
    );
}

/// One machine's sums after the first `k` passes of [`SPP`], pass by
/// pass as a render with a noise target adds them.
fn sums_after(k: usize) -> Vec<PixelSum> {
    let mut st = TraceStats::default();
    (0..H)
        .flat_map(|y| (0..W).map(move |x| (x, y)))
        .map(|(x, y)| {
            let mut p = PixelSum::default();
            for pass in passes(SPP).into_iter().take(k) {
                let m = locus_core::passes::pass_sum(pass, &mut st, |s, _| sample(x, y, s));
                p.add_pass(m);
            }
            p
        })
        .collect()
}

/// Adds every unit of the passes open now; returns how many.
fn add_open(f: &mut Film) -> usize {
    let open: Vec<Unit> = f
        .missing()
        .into_iter()
        .filter(|u| u.pass < f.open_passes())
        .collect();
    for u in &open {
        let s = render(f, *u);
        f.add(*u, s).unwrap();
    }
    open.len()
}

#[test]
fn a_noise_target_opens_one_pass_at_a_time_and_stops_where_one_machine_does() {
    // 13 spp: passes end at 2, 4, 7 and 13 samples. A target between
    // the estimates after 4 and after 7 samples is met after 7.
    let est = |k: usize| {
        let end = passes(SPP)[k - 1].end;
        locus_core::metrics::estimate_error_of_sums(&sums_after(k), end).unwrap()
    };
    let target = (est(2).rel_mse * est(3).rel_mse).sqrt();
    assert!(est(3).rel_mse < target && target < est(2).rel_mse);
    let mut f = film().with_target(Some(target));
    assert_eq!(f.open_passes(), 1, "the first pass alone");
    for pass in 0..3u32 {
        assert_eq!(f.pass(), pass);
        assert_eq!(f.open_passes(), pass + 1, "the next pass waits");
        assert!(!f.is_complete());
        assert_eq!(add_open(&mut f), f.tiles().len());
    }
    assert!(f.is_complete(), "met after the third pass");
    assert_eq!(f.open_passes(), 3, "the fourth is never handed out");
    assert!(f.missing().is_empty());
    assert_eq!(f.spp_done(), 7);
    let want: Vec<[f32; 3]> = sums_after(3).iter().map(|p| p.mean(7)).collect();
    assert_eq!(f.image().pixels, want);
    assert_eq!(f.error_estimate(), Some(est(3)));
    let late = Unit { tile: 0, pass: 3 };
    let s = render(&f, late);
    assert_eq!(f.add(late, s), Err(Refused::Unknown));

    // A scheduler restarted on its stored tiles judges them as the
    // running job did: stopped when every tile holds the passes kept,
    // going on when some hold a pass more than the others (then the
    // earlier pass was judged and not met).
    let mut again = film().with_target(Some(target));
    for t in 0..f.tiles().len() as u32 {
        assert!(again.restore(t, f.tile_sums(t)));
    }
    again.resume();
    assert!(again.is_complete());
    assert_eq!(again.error_estimate(), Some(est(3)));
    let mut mixed = film().with_target(Some(target));
    add_open(&mut mixed);
    add_open(&mut mixed);
    let u = Unit { tile: 1, pass: 2 };
    let s = render(&mixed, u);
    mixed.add(u, s).unwrap();
    let mut resumed = film().with_target(Some(target));
    for t in 0..mixed.tiles().len() as u32 {
        assert!(resumed.restore(t, mixed.tile_sums(t)));
    }
    resumed.resume();
    assert!(!resumed.is_complete());
    assert_eq!(resumed.open_passes(), 3);
    while !resumed.is_complete() {
        assert!(add_open(&mut resumed) > 0);
    }
    assert_eq!(resumed.image().pixels, want);

    // A target never met renders every pass, as without one.
    let mut all = film().with_target(Some(1e-30));
    while !all.is_complete() {
        add_open(&mut all);
    }
    assert_eq!(all.image().pixels, one_machine());
    assert_eq!(all.error_estimate(), Some(one_machine_estimate()));
}

/// One machine's adaptive render of [`sample`] at `spp`, as
/// `locus_core::render` runs it: each pixel's sums and count.
fn one_machine_adaptive(spp: u32) -> (Vec<PixelSum>, Vec<u32>) {
    let n = (W * H) as usize;
    let (mut sums, mut counts) = (vec![PixelSum::default(); n], vec![0u32; n]);
    let mut st = TraceStats::default();
    for pass in passes(spp) {
        let given = if pass.start >= spread::pilot_end(spp) {
            let budget = pass.len() as u64 * n as u64;
            spread::spread(W, H, &sums, &counts, budget, spp * spread::MAX_SHARE)
        } else {
            vec![pass.len() as u32; n]
        };
        for i in 0..n {
            let (x, y) = (i as u32 % W, i as u32 / W);
            if given[i] > 0 {
                let range = counts[i]..counts[i] + given[i];
                let m = locus_core::passes::pass_sum(range, &mut st, |s, _| sample(x, y, s));
                sums[i].add_pass(m);
                counts[i] += given[i];
            }
        }
    }
    (sums, counts)
}

#[test]
fn adaptive_sampling_spreads_as_one_machine_and_survives_a_restart() {
    // 32 spp: passes end at 1, 2, 4, 8, 16 and 32; the pilot is the
    // first four, the last two are spread.
    const SPP: u32 = 32;
    let film = || Film::new(W, H, SPP, tiles(W, H, 3, TileOrder::Scanline)).with_adaptive(true);
    let (sums, counts) = one_machine_adaptive(SPP);
    assert!(counts.iter().min() < counts.iter().max(), "{counts:?}");
    let want: Vec<[f32; 3]> = sums.iter().zip(&counts).map(|(p, &n)| p.mean(n)).collect();
    let estimate = estimate_error_of_counted(sums.iter().zip(counts.iter().copied()), SPP);
    let mut f = film();
    let mut opened = 0;
    while !f.is_complete() {
        assert_eq!(f.open_passes(), f.pass() + 1, "one pass at a time");
        assert!(add_open(&mut f) > 0);
        opened += 1;
    }
    assert_eq!(opened, passes(SPP).len());
    assert_eq!(f.image().pixels, want);
    assert_eq!(f.sample_counts(), Some(&counts[..]));
    assert_eq!(f.samples(), ((W * H * SPP) as u64, (W * H * SPP) as u64));
    assert_eq!(f.error_estimate(), estimate);

    // A scheduler restarted in the first spread pass, tile 0 having
    // rendered it and the others not: the spread the store kept gives
    // the others the samples they would have had.
    let mut part = film();
    while part.pass() < 4 {
        add_open(&mut part);
    }
    let u = Unit { tile: 0, pass: 4 };
    let a = part.assignment(u, 3, 0);
    assert!(matches!(a.samples, PassSamples::Spread { .. }), "{a:?}");
    let s = render(&part, u);
    part.add(u, s).unwrap();
    let restart = |keep_spread: bool| {
        let mut again = film();
        for t in 0..part.tiles().len() as u32 {
            assert!(again.restore(t, part.tile_sums(t)));
        }
        let spread = part.pass_spread().cloned().expect("pass 4 is spread");
        assert_eq!(spread.pass, 4);
        if keep_spread {
            assert!(again.restore_spread(spread));
        }
        again.resume();
        while !again.is_complete() {
            assert!(add_open(&mut again) > 0);
        }
        again
    };
    let again = restart(true);
    assert_eq!(again.image().pixels, want);
    assert_eq!(again.sample_counts(), Some(&counts[..]));
    // Without it the pass is spread again from the film as restored:
    // every pixel still gets its pilot and more.
    let spread_again = restart(false);
    let c = spread_again.sample_counts().unwrap();
    assert!(c.iter().all(|&n| n >= spread::pilot_end(SPP)), "{c:?}");
    assert_ne!(c, &counts[..]);
}
