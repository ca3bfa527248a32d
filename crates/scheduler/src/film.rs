//! The running job's film: per pixel, the sum of its tile's passes so far
//! ([`locus_core::passes`]), added in pass order however the passes
//! arrive, so that the image is bit-identical to one machine's.
//!
//! With a noise target (`target_rel_mse`), the film is judged whenever a
//! pass is complete, as one machine judges its image after each pass
//! ([`locus_core::metrics::meets_target`] of the same sums): once the
//! estimate meets the target, no later pass is rendered. For that, no tile
//! may hold a later pass than the others when one is judged, so the
//! scheduler hands out a pass only once the one before is complete
//! ([`Film::open_passes`]): a barrier at each pass end, paid only by jobs
//! with a target or adaptive sampling.
//!
//! With adaptive sampling, a pass after the pilot gives its samples to
//! the pixels by [`locus_core::spread::spread`] of the film's sums when
//! the pass opens, as one machine does at the same pass end: the same
//! barrier, the same sums, so the same counts to the bit. Each pixel then
//! takes the next samples of its own sequence (a tile's
//! [`PassSamples::Spread`]).
//!
//! A tile's pass that arrives before an earlier pass of the same tile is
//! held until that one is in. The scheduler hands passes out in order
//! (every tile of a pass before the next pass), so what is held is
//! bounded by the tiles in flight. Counts are kept as the film fills, so
//! progress is O(passes) to read, not O(tiles).

use locus_core::image_io::Image;
use locus_core::metrics::{ErrorEstimate, estimate_error_of_counted, meets_target_counted};
use locus_core::passes::{Moments, PixelSum, passes};
use locus_core::render::Tile;
use locus_core::spread;
use locus_protocol::control::{PassSamples, TileAssignment};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::ops::Range;

/// A tile in one pass: what the scheduler hands out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Unit {
    pub tile: u32,
    pub pass: u32,
}

/// A tile as the store keeps it: its passes in so far, its pixels' sums
/// over them and how many samples each has.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileSums {
    pub passes: u32,
    pub sums: Vec<Moments>,
    pub counts: Vec<u32>,
}

/// With adaptive sampling, the open pass whose samples are spread and the
/// samples each pixel takes in it (row-major), as the film made it and
/// the store keeps it: a scheduler restarted once some tiles hold that
/// pass cannot make it again, since it came from their sums before it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PassSpread {
    pub pass: u32,
    pub given: Vec<u32>,
}

/// Why a tile's pass was not taken.
#[derive(Debug, PartialEq)]
pub enum Refused {
    /// No such tile or pass.
    Unknown,
    /// Already in (or held): a late copy.
    Duplicate,
    /// The wrong number of pixels: a broken worker.
    Size { got: usize, want: u32 },
}

pub struct Film {
    width: u32,
    spp: u32,
    tiles: Vec<Tile>,
    passes: Vec<Range<u32>>,
    sums: Vec<PixelSum>,
    /// Samples in each pixel's sums.
    counts: Vec<u32>,
    /// Passes added to each tile, in order.
    passes_in: Vec<u32>,
    /// `complete[p]`: tiles whose pass `p` is added.
    complete: Vec<u32>,
    /// Passes that came before an earlier pass of their tile.
    early: BTreeMap<Unit, Vec<Moments>>,
    samples_done: u64,
    /// The noise target (an estimated relMSE), if the job has one.
    target: Option<f64>,
    /// The passes kept once the target was met: later ones are never
    /// rendered.
    kept: Option<u32>,
    /// Adaptive sampling ([`spread`]).
    adaptive: bool,
    /// With adaptive sampling, the open pass's spread, if it is spread.
    spread: Option<PassSpread>,
    /// The spread the store kept, until [`Film::resume`].
    stored_spread: Option<PassSpread>,
}

impl Film {
    /// An empty film of `width` by `height` pixels at `spp` samples per
    /// pixel, cut into `tiles`.
    pub fn new(width: u32, height: u32, spp: u32, tiles: Vec<Tile>) -> Self {
        let passes = passes(spp);
        Self {
            width,
            spp: spp.max(1),
            passes_in: vec![0; tiles.len()],
            complete: vec![0; passes.len()],
            tiles,
            passes,
            sums: vec![PixelSum::default(); width as usize * height as usize],
            counts: vec![0; width as usize * height as usize],
            early: BTreeMap::new(),
            samples_done: 0,
            target: None,
            kept: None,
            adaptive: false,
            spread: None,
            stored_spread: None,
        }
    }

    /// The film of a job with adaptive sampling: each pass after the pilot
    /// spreads its samples by the pixels' noise, opened one at a time.
    pub fn with_adaptive(mut self, adaptive: bool) -> Self {
        self.adaptive = adaptive;
        self
    }

    /// The film of a job with a noise target: it stops after the first
    /// pass whose estimated relMSE is at or below `target`.
    pub fn with_target(mut self, target: Option<f64>) -> Self {
        self.target = target;
        self
    }

    /// How many passes may be handed out: every pass, or with a noise
    /// target or adaptive sampling those up to the first incomplete one
    /// (none past the passes kept once the target is met).
    pub fn open_passes(&self) -> u32 {
        let all = self.passes.len() as u32;
        match (self.target.is_some() || self.adaptive, self.kept) {
            (_, Some(k)) => k,
            (true, None) => (self.pass() + 1).min(all),
            (false, None) => all,
        }
    }

    /// Each pixel's sums with its count, row-major.
    fn counted(&self) -> impl Iterator<Item = (&PixelSum, u32)> {
        self.sums.iter().zip(self.counts.iter().copied())
    }

    /// Judges the film against its target once pass `k - 1` is complete
    /// and no tile holds a later one (the pixels' sums are then those of
    /// `k` passes everywhere).
    fn judge(&mut self, k: u32) {
        let (Some(t), None) = (self.target, self.kept) else {
            return;
        };
        if k == 0 || k as usize >= self.passes.len() || self.complete[k as usize] > 0 {
            return;
        }
        let samples = self.passes[k as usize - 1].end;
        if meets_target_counted(self.counted(), samples, t) {
            self.kept = Some(k);
        }
    }

    /// With adaptive sampling, spreads the samples of pass `k`, which
    /// opens now that the passes before it are complete, as one machine
    /// spreads them after the same passes: nothing for the pilot's passes,
    /// or once the target is met.
    fn open_spread(&mut self, k: u32) {
        self.spread = None;
        let Some(pass) = self.passes.get(k as usize) else {
            return;
        };
        if !self.adaptive || k >= self.kept_or_all() || pass.start < spread::pilot_end(self.spp) {
            return;
        }
        let height = (self.sums.len() / self.width.max(1) as usize) as u32;
        let budget = pass.len() as u64 * self.sums.len() as u64;
        let cap = self.spp.saturating_mul(spread::MAX_SHARE);
        let given = spread::spread(self.width, height, &self.sums, &self.counts, budget, cap);
        self.spread = Some(PassSpread { pass: k, given });
    }

    /// The open pass's spread, with adaptive sampling once one is open:
    /// what the store keeps when it opens.
    pub fn pass_spread(&self) -> Option<&PassSpread> {
        self.spread.as_ref()
    }

    /// Puts back the spread the store kept, for [`Film::resume`], if it
    /// fits the film.
    pub fn restore_spread(&mut self, kept: PassSpread) -> bool {
        let fits = self.adaptive && kept.given.len() == self.sums.len();
        if fits {
            self.stored_spread = Some(kept);
        }
        fits
    }

    /// After tiles were restored from the store: judges the film as the
    /// running job would have when its last complete pass came in, and
    /// with adaptive sampling opens the next pass's spread: the one the
    /// store kept if it is that pass's (some tiles may hold the pass
    /// already, and the spread was made before they did), or else one made
    /// from the film as restored (the same where no tile holds the pass).
    pub fn resume(&mut self) {
        let k = self.pass();
        self.judge(k);
        self.open_spread(k);
        let kept = self.stored_spread.take();
        if let (Some(open), Some(kept)) = (&mut self.spread, kept)
            && kept.pass == k
        {
            *open = kept;
        }
    }

    pub fn tiles(&self) -> &[Tile] {
        &self.tiles
    }

    pub fn passes(&self) -> &[Range<u32>] {
        &self.passes
    }

    /// Tile `u.tile` as a worker renders it in pass `u.pass`, handed out
    /// with `queue_share` (see [`TileAssignment::queue_share`]).
    pub fn assignment(&self, u: Unit, run: u64, queue_share: u64) -> TileAssignment {
        let r = &self.passes[u.pass as usize];
        let t = self.tiles[u.tile as usize];
        let samples = match &self.spread {
            // The tile's pixels have the passes before this one.
            Some(sp) if sp.pass == u.pass => PassSamples::Spread {
                first: self.of_tile(t, &self.counts),
                count: self.of_tile(t, &sp.given),
            },
            _ => PassSamples::Even([r.start, r.end]),
        };
        TileAssignment {
            job: run,
            tile: u.tile,
            pass: u.pass,
            samples,
            x0: t.x0,
            y0: t.y0,
            x1: t.x1,
            y1: t.y1,
            queue_share,
        }
    }

    /// Camera samples in each tile pass, by tile and pass: a spread pass's
    /// tiles hold as many in all, shared unevenly.
    pub fn sizes(&self) -> crate::tiles::Sizes {
        crate::tiles::Sizes {
            tile_pixels: self.tiles.iter().map(|t| u64::from(t.pixels())).collect(),
            pass_samples: self.passes.iter().map(|r| r.len() as u64).collect(),
        }
    }

    /// Whether tile `u.tile`'s pass `u.pass` is in (added or held).
    pub fn has(&self, u: Unit) -> bool {
        u.pass < self.passes_in[u.tile as usize] || self.early.contains_key(&u)
    }

    /// The units not yet in, pass by pass, tiles in the job's (shuffled)
    /// order within each.
    pub fn missing(&self) -> Vec<Unit> {
        (0..self.passes.len() as u32)
            .flat_map(|pass| (0..self.tiles.len() as u32).map(move |tile| Unit { tile, pass }))
            .filter(|&u| !self.has(u) && u.pass < self.kept_or_all())
            .collect()
    }

    /// Takes tile `u.tile`'s sums of pass `u.pass`. Returns whether the
    /// tile's state in the film changed (an earlier pass was not held up).
    pub fn add(&mut self, u: Unit, sums: Vec<Moments>) -> Result<bool, Refused> {
        let Some(t) = self.tiles.get(u.tile as usize) else {
            return Err(Refused::Unknown);
        };
        if u.pass as usize >= self.passes.len() || u.pass >= self.kept_or_all() {
            return Err(Refused::Unknown);
        }
        if sums.len() != t.pixels() as usize {
            return Err(Refused::Size {
                got: sums.len(),
                want: t.pixels(),
            });
        }
        if self.has(u) {
            return Err(Refused::Duplicate);
        }
        if u.pass > self.passes_in[u.tile as usize] {
            self.early.insert(u, sums);
            return Ok(false);
        }
        self.add_in_order(u.tile, &sums);
        loop {
            let next = Unit {
                tile: u.tile,
                pass: self.passes_in[u.tile as usize],
            };
            let Some(s) = self.early.remove(&next) else {
                break;
            };
            self.add_in_order(u.tile, &s);
        }
        Ok(true)
    }

    /// The film's pixel indices of tile `t`, row by row, in the row-major
    /// order of a tile's results.
    fn rows(&self, t: Tile) -> impl Iterator<Item = Range<usize>> + use<> {
        let width = self.width;
        (t.y0..t.y1).map(move |y| {
            let at = (y * width + t.x0) as usize;
            at..at + (t.x1 - t.x0) as usize
        })
    }

    /// Tile `t`'s pixels' entries of the per-pixel `values`, in the
    /// row-major order of a tile's results.
    fn of_tile<T: Copy>(&self, t: Tile, values: &[T]) -> Vec<T> {
        self.rows(t).flat_map(|row| &values[row]).copied().collect()
    }

    /// Sets or adds to tile `t`'s pixels from its row-major `sums`.
    fn each_pixel(&mut self, t: Tile, sums: &[Moments], f: impl Fn(&mut PixelSum, Moments)) {
        let mut from = sums.iter();
        for row in self.rows(t) {
            for (p, s) in self.sums[row].iter_mut().zip(&mut from) {
                f(p, *s);
            }
        }
    }

    /// Adds tile `tile`'s next pass. A pixel given no samples in a spread
    /// pass keeps its sums as they are, as one machine's do.
    fn add_in_order(&mut self, tile: u32, sums: &[Moments]) {
        let t = self.tiles[tile as usize];
        let pass = self.passes_in[tile as usize];
        let even = self.passes[pass as usize].len() as u32;
        let given = match &self.spread {
            Some(sp) if sp.pass == pass => Some(&sp.given),
            _ => None,
        };
        let mut from = sums.iter();
        for i in self.rows(t).flatten() {
            let s = from.next().expect("a sum a pixel, checked by add");
            let n = given.map_or(even, |g| g[i]);
            if n > 0 {
                self.sums[i].add_pass(*s);
                self.counts[i] += n;
                self.samples_done += u64::from(n);
            }
        }
        self.complete[pass as usize] += 1;
        self.passes_in[tile as usize] += 1;
        if self.complete[pass as usize] == self.tiles.len() as u32 {
            self.judge(pass + 1);
            self.open_spread(pass + 1);
        }
    }

    /// The passes the film ends with: all, or those kept at the target.
    fn kept_or_all(&self) -> u32 {
        self.kept.unwrap_or(self.passes.len() as u32)
    }

    /// Samples each pixel has once every tile's passes so far are in: the
    /// image's samples per pixel when the film is complete.
    pub fn spp_done(&self) -> u32 {
        match self.pass() {
            0 => 0,
            k => self.passes[k as usize - 1].end,
        }
    }

    /// What the store keeps of tile `tile`.
    pub fn tile_sums(&self, tile: u32) -> TileSums {
        let t = self.tiles[tile as usize];
        let sums = self
            .rows(t)
            .flat_map(|row| self.sums[row].iter().map(PixelSum::total))
            .collect();
        TileSums {
            passes: self.passes_in[tile as usize],
            sums,
            counts: self.of_tile(t, &self.counts),
        }
    }

    /// Puts back a tile the store kept, if it fits this film and the
    /// tile has nothing yet. Returns whether it did.
    pub fn restore(&mut self, tile: u32, kept: TileSums) -> bool {
        let Some(&t) = self.tiles.get(tile as usize) else {
            return false;
        };
        let pixels = t.pixels() as usize;
        if kept.passes == 0
            || kept.passes as usize > self.passes.len()
            || kept.sums.len() != pixels
            || kept.counts.len() != pixels
            || self.passes_in[tile as usize] != 0
        {
            return false;
        }
        // Each pixel's count: the passes' samples, or with adaptive
        // sampling at least the pilot's and at most the cap.
        let end = self.passes[kept.passes as usize - 1].end;
        let cap = self.spp.saturating_mul(spread::MAX_SHARE);
        let pilot = spread::pilot_end(self.spp).min(end);
        let fits = |&n: &u32| match self.adaptive {
            false => n == end,
            true => (pilot..=cap).contains(&n),
        };
        if !kept.counts.iter().all(fits) {
            return false;
        }
        self.each_pixel(t, &kept.sums, |p, s| *p = PixelSum::from_total(s));
        let mut from = kept.counts.iter();
        for i in self.rows(t).flatten() {
            self.counts[i] = *from.next().expect("checked above");
        }
        self.passes_in[tile as usize] = kept.passes;
        self.samples_done += kept.counts.iter().map(|&n| u64::from(n)).sum::<u64>();
        for c in &mut self.complete[..kept.passes as usize] {
            *c += 1;
        }
        true
    }

    /// Pixel samples in the film, of how many in all.
    pub fn samples(&self) -> (u64, u64) {
        (self.samples_done, self.sums.len() as u64 * self.spp as u64)
    }

    /// The earliest pass not complete (`passes().len()` when all are).
    pub fn pass(&self) -> u32 {
        let n = self.tiles.len() as u32;
        self.complete
            .iter()
            .position(|&c| c < n)
            .unwrap_or(self.complete.len()) as u32
    }

    /// Tile passes in the film (added), of how many in all.
    pub fn units(&self) -> (u64, u64) {
        let done = self.complete.iter().map(|&c| c as u64).sum();
        (done, self.tiles.len() as u64 * self.passes.len() as u64)
    }

    /// Tile passes and pixel samples in the film.
    pub fn done(&self) -> (u64, u64) {
        (self.units().0, self.samples_done)
    }

    /// Whether every pass is in, or every pass kept once the noise target
    /// was met.
    pub fn is_complete(&self) -> bool {
        self.pass() == self.kept_or_all()
    }

    /// The image so far: each pixel the mean of its tile's passes in (the
    /// finished image once complete); black where none is.
    pub fn image(&self) -> Image {
        let height = (self.sums.len() / self.width.max(1) as usize) as u32;
        let mut img = Image::new(self.width, height);
        for (px, (p, n)) in img.pixels.iter_mut().zip(self.counted()) {
            if n > 0 {
                *px = p.mean(n);
            }
        }
        img
    }

    /// With adaptive sampling, the samples each pixel has (row-major).
    pub fn sample_counts(&self) -> Option<&[u32]> {
        self.adaptive.then_some(&self.counts[..])
    }

    /// The error the finished image carries, from its samples' spread, as
    /// one machine's report gives it (None before the film is complete, or
    /// for one sample a pixel).
    pub fn error_estimate(&self) -> Option<ErrorEstimate> {
        self.is_complete()
            .then(|| estimate_error_of_counted(self.counted(), self.spp_done()))
            .flatten()
    }
}

#[cfg(test)]
mod tests;
