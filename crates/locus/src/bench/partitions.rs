//! Region growing against the Morton baseline, as `locus bench-farm`
//! measures them under `forward`: does region growing forward fewer
//! queries at equal or better load imbalance?
//!
//! One run cannot say. The same configuration's CPU imbalance moves by
//! 0.01-0.04 from run to run on two workers (a worker waits for answers at
//! random moments, most of all while the last samples drain), as much as
//! the two partitions differ there. So every run of a configuration is
//! kept ([`RunFigures`]) and the two partitions are compared by their
//! means, a difference within two standard errors of it read as equal.
//!
//! Three imbalances are compared, each the busiest worker's over the mean:
//! - traced: BVH steps, the tracing the partition places, which tile
//!   stealing and waiting do not move;
//! - render CPU ([`FarmReport::load_imbalance`]);
//! - CPU with setup ([`FarmReport::total_imbalance`]), the criterion: a
//!   region's build is load the partition places too. A worker whose
//!   region has fewer triangles starts rendering first and takes more
//!   tiles; the render-CPU figure counts that as imbalance, though it is
//!   the demand-driven tiles evening out the builds, and misses a region
//!   whose long build its peers made up for.

use super::farm::Row;
use locus_protocol::report::FarmReport;
use serde::Serialize;
use std::fmt::Write as _;

/// What one farm run says of its partition.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RunFigures {
    /// Most render CPU of a worker over the mean ([`FarmReport::load_imbalance`]).
    pub imbalance: f64,
    /// The same with each worker's setup ([`FarmReport::total_imbalance`]).
    pub total_imbalance: f64,
    /// Most BVH steps (nodes and triangle tests) of a worker over the mean.
    pub traced_imbalance: f64,
    pub forwards_per_ray: f64,
}

impl RunFigures {
    pub fn of(f: &FarmReport) -> Self {
        let steps: Vec<f64> = f
            .workers
            .iter()
            .map(|w| (w.stats.trace.bvh_nodes + w.stats.trace.tri_tests) as f64)
            .collect();
        let mean = steps.iter().sum::<f64>() / steps.len().max(1) as f64;
        let most = steps.iter().copied().fold(0.0, f64::max);
        Self {
            imbalance: f.load_imbalance,
            total_imbalance: f.total_imbalance,
            traced_imbalance: if mean > 0.0 { most / mean } else { 1.0 },
            forwards_per_ray: f.forwarded_fraction,
        }
    }
}

/// A mean over runs and its standard error (0 for one run: unknown, and
/// then no difference reads as equal).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Spread {
    pub mean: f64,
    pub se: f64,
    pub n: usize,
}

impl Spread {
    pub fn of(v: impl Iterator<Item = f64>) -> Self {
        let v: Vec<f64> = v.collect();
        let n = v.len();
        let mean = v.iter().sum::<f64>() / n.max(1) as f64;
        let se = if n > 1 {
            let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
            (var / n as f64).sqrt()
        } else {
            0.0
        };
        Self { mean, se, n }
    }
}

/// How region growing's mean stands to Morton's: lower, equal within two
/// standard errors of the difference, or higher.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum Verdict {
    Lower,
    Equal,
    Higher,
}

impl Verdict {
    pub fn of(rg: Spread, morton: Spread) -> Self {
        let d = rg.mean - morton.mean;
        let bound = 2.0 * (rg.se.powi(2) + morton.se.powi(2)).sqrt();
        if d.abs() <= bound {
            Verdict::Equal
        } else if d < 0.0 {
            Verdict::Lower
        } else {
            Verdict::Higher
        }
    }

    fn word(self) -> &'static str {
        match self {
            Verdict::Lower => "lower",
            Verdict::Equal => "equal",
            Verdict::Higher => "HIGHER",
        }
    }
}

/// One scene and farm size: region growing (`rg`) against Morton.
#[derive(Clone, Debug, Serialize)]
pub struct Comparison {
    pub scene: String,
    pub workers: usize,
    pub shared_percent: u32,
    pub forwards: [Spread; 2],
    pub traced: [Spread; 2],
    pub imbalance: [Spread; 2],
    pub total: [Spread; 2],
    /// Region growing forwards fewer queries a ray, beyond noise.
    pub fewer_forwards: bool,
    pub traced_verdict: Verdict,
    pub imbalance_verdict: Verdict,
    pub total_verdict: Verdict,
}

impl Comparison {
    /// The criterion: fewer forwards at equal or better imbalance of the
    /// CPU time the partition places, setup included.
    pub fn holds(&self) -> bool {
        self.fewer_forwards && self.total_verdict != Verdict::Higher
    }
}

/// Every pair of `forward` rows, region growing and Morton, of the same
/// scene, farm size and shared percent (random polling left out).
pub fn compare(rows: &[Row]) -> Vec<Comparison> {
    let forward = |r: &&Row| r.policy == "forward" && !r.random_polling && r.workers > 1;
    rows.iter()
        .filter(forward)
        .filter(|r| r.partitioner == "RegionGrowing")
        .filter_map(|rg| {
            let m = rows.iter().filter(forward).find(|m| {
                m.partitioner == "Morton"
                    && m.scene == rg.scene
                    && m.workers == rg.workers
                    && m.shared_percent == rg.shared_percent
            })?;
            let spread = |r: &Row, f: fn(&RunFigures) -> f64| Spread::of(r.runs.iter().map(f));
            let pair = |f: fn(&RunFigures) -> f64| [spread(rg, f), spread(m, f)];
            let forwards = pair(|x| x.forwards_per_ray);
            let traced = pair(|x| x.traced_imbalance);
            let imbalance = pair(|x| x.imbalance);
            let total = pair(|x| x.total_imbalance);
            Some(Comparison {
                scene: rg.scene.clone(),
                workers: rg.workers,
                shared_percent: rg.shared_percent,
                forwards,
                traced,
                imbalance,
                total,
                fewer_forwards: Verdict::of(forwards[0], forwards[1]) == Verdict::Lower,
                traced_verdict: Verdict::of(traced[0], traced[1]),
                imbalance_verdict: Verdict::of(imbalance[0], imbalance[1]),
                total_verdict: Verdict::of(total[0], total[1]),
            })
        })
        .collect()
}

fn cell(s: Spread, digits: usize) -> String {
    if s.n > 1 {
        format!("{:.digits$} ± {:.digits$}", s.mean, s.se)
    } else {
        format!("{:.digits$}", s.mean)
    }
}

/// The comparisons as a Markdown table (empty without any).
pub fn markdown(c: &[Comparison]) -> String {
    if c.is_empty() {
        return String::new();
    }
    let mut s = String::from(
        "Region growing (RG) against Morton under `forward`: means over runs ± their standard error; imbalances are the busiest worker's over the mean; RG's is \"lower\", \"equal\" (a difference within two standard errors) or \"HIGHER\".\n\n| scene | workers | shared | runs | forwards / ray, RG / Morton | traced imbalance, RG / Morton | render CPU imbalance, RG / Morton | CPU imbalance with setup, RG / Morton | traced | render CPU | with setup | fewer forwards at equal or better imbalance with setup |\n|---|---:|---:|---:|---|---|---|---|---|---|---|---|\n",
    );
    for x in c {
        let _ = writeln!(
            s,
            "| {} | {} | {}% | {} / {} | {} / {} | {} / {} | {} / {} | {} / {} | {} | {} | {} | {} |",
            x.scene,
            x.workers,
            x.shared_percent,
            x.imbalance[0].n,
            x.imbalance[1].n,
            cell(x.forwards[0], 3),
            cell(x.forwards[1], 3),
            cell(x.traced[0], 3),
            cell(x.traced[1], 3),
            cell(x.imbalance[0], 3),
            cell(x.imbalance[1], 3),
            cell(x.total[0], 3),
            cell(x.total[1], 3),
            x.traced_verdict.word(),
            x.imbalance_verdict.word(),
            x.total_verdict.word(),
            if x.holds() { "yes" } else { "NO" },
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run's traced imbalance is its busiest worker's BVH steps (nodes
    /// and triangle tests) over the mean; the rest comes from its report.
    #[test]
    fn a_runs_figures_come_from_its_report() {
        use locus_core::stats::TraceStats;
        use locus_protocol::report::{WorkerStats, WorkerSummary};
        let worker = |bvh_nodes, tri_tests| WorkerSummary {
            stats: WorkerStats {
                trace: TraceStats {
                    bvh_nodes,
                    tri_tests,
                    ..TraceStats::default()
                },
                ..WorkerStats::default()
            },
            ..WorkerSummary::default()
        };
        let f = FarmReport {
            load_imbalance: 1.2,
            total_imbalance: 1.1,
            forwarded_fraction: 0.3,
            workers: vec![worker(100, 50), worker(200, 100)],
            ..FarmReport::default()
        };
        let r = RunFigures::of(&f);
        assert!((r.traced_imbalance - 300.0 / 225.0).abs() < 1e-12, "{r:?}");
        assert_eq!(
            (r.imbalance, r.total_imbalance, r.forwards_per_ray),
            (1.2, 1.1, 0.3)
        );
    }

    fn spread(v: &[f64]) -> Spread {
        Spread::of(v.iter().copied())
    }

    /// The standard error is the sample deviation over the root of n.
    #[test]
    fn a_spread_is_the_mean_and_its_standard_error() {
        let s = spread(&[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(s.n, 4);
        assert!((s.mean - 2.5).abs() < 1e-12);
        // Sample variance 5/3; over 4 runs.
        assert!((s.se - (5.0f64 / 3.0 / 4.0).sqrt()).abs() < 1e-12, "{s:?}");
        assert_eq!(spread(&[1.5]).se, 0.0);
    }

    /// Within two standard errors of the difference is equal; beyond, the
    /// side of the difference; one run each has no noise to hide in.
    #[test]
    fn verdicts_follow_the_difference_against_its_noise() {
        let a = spread(&[1.00, 1.02, 1.04]);
        let b = spread(&[1.01, 1.03, 1.05]);
        assert_eq!(Verdict::of(a, b), Verdict::Equal);
        let low = spread(&[1.00, 1.001, 1.002]);
        let high = spread(&[1.10, 1.101, 1.102]);
        assert_eq!(Verdict::of(low, high), Verdict::Lower);
        assert_eq!(Verdict::of(high, low), Verdict::Higher);
        assert_eq!(Verdict::of(spread(&[1.0]), spread(&[1.01])), Verdict::Lower);
        assert_eq!(Verdict::of(spread(&[1.0]), spread(&[1.0])), Verdict::Equal);
    }

    /// (render CPU imbalance, with setup, traced, forwards a ray) a run.
    fn row(scene: &str, partitioner: &str, workers: usize, runs: &[(f64, f64, f64, f64)]) -> Row {
        let mut r = Row::blank(scene);
        r.policy = "forward".into();
        r.partitioner = partitioner.into();
        r.workers = workers;
        r.shared_percent = 10;
        r.runs = runs
            .iter()
            .map(
                |&(imbalance, total_imbalance, traced_imbalance, forwards_per_ray)| RunFigures {
                    imbalance,
                    total_imbalance,
                    traced_imbalance,
                    forwards_per_ray,
                },
            )
            .collect();
        r
    }

    /// Rows pair by scene, farm size and shared percent; the criterion
    /// holds with fewer forwards at an imbalance with setup not beyond
    /// noise higher, whatever the render CPU's, and fails on a higher one.
    #[test]
    fn region_growing_pairs_with_morton_and_is_judged_over_runs() {
        let rows = vec![
            row(
                "room",
                "RegionGrowing",
                2,
                &[(1.05, 1.03, 1.03, 0.30), (1.04, 1.01, 1.03, 0.29)],
            ),
            row(
                "room",
                "Morton",
                2,
                &[(1.00, 1.00, 1.06, 0.31), (1.01, 1.02, 1.05, 0.312)],
            ),
            row(
                "room",
                "RegionGrowing",
                4,
                &[(1.0, 1.20, 1.04, 0.53), (1.0, 1.21, 1.04, 0.531)],
            ),
            row(
                "room",
                "Morton",
                4,
                &[(1.1, 1.10, 1.23, 0.72), (1.1, 1.11, 1.22, 0.74)],
            ),
            row("other", "Morton", 2, &[(1.0, 1.0, 1.0, 0.1)]),
        ];
        let c = compare(&rows);
        assert_eq!(c.len(), 2, "{c:?}");
        assert_eq!((c[0].workers, c[1].workers), (2, 4));
        assert!(c[0].fewer_forwards);
        assert_eq!(c[0].imbalance_verdict, Verdict::Higher);
        assert_eq!(c[0].total_verdict, Verdict::Equal);
        assert_eq!(c[0].traced_verdict, Verdict::Lower);
        assert!(c[0].holds());
        assert_eq!(c[1].imbalance_verdict, Verdict::Lower);
        assert_eq!(c[1].total_verdict, Verdict::Higher);
        assert!(!c[1].holds());
        let md = markdown(&c);
        assert!(md.contains("| room | 2 | 10% | 2 / 2 |"), "{md}");
        assert!(md.contains("| NO |"), "{md}");
    }
}
