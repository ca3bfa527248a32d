//! The benchmarks, apart from the render and farm paths they measure:
//! [`trace`] (`locus bench`: BVH build, ray throughput against raw obvhs,
//! samples per second), [`locality`] (`locus bench locality`: Jansen and
//! Reinhard's Tables 1-3, partitioners and fetch policies side by side)
//! [`quality`] (`locus bench quality`: error per second against Mitsuba
//! 3) and [`farm`] (`locus bench-farm`: the farm against one machine on the
//! same cores, and its scaling, written out by [`farm_table`], with
//! [`partitions`] judging region growing against the Morton baseline over
//! its runs). Each writes Markdown and CSV (and SVG
//! plots) that the README quotes, with ratios taken within one run.

pub mod farm;
pub mod farm_table;
pub mod locality;
pub mod partitions;
pub mod quality;
pub mod trace;
