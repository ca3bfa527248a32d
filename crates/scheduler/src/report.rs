//! The report of a finished job: per-worker counters as the workers
//! counted them, and the job's derived figures.

use crate::actor::Running;
use crate::cost;
use locus_protocol::report::{FarmReport, Phases, Prediction, WorkerStats, WorkerSummary};
use locus_protocol::submit::CostModel;
use std::time::Instant;

/// The report of job `j`, whose last attempt's workers are `names` (their
/// peer addresses, in job order). Counters are the last attempt's.
pub fn build_report(j: &Running, names: &[String]) -> FarmReport {
    let a = &j.attempt;
    let prep = a.prep.as_ref().expect("prepared before reporting");
    let stats: Vec<WorkerStats> = a
        .reports
        .iter()
        .map(|r| r.clone().unwrap_or_default())
        .collect();
    let work: Vec<f64> = stats
        .iter()
        .map(|s| (s.trace.bvh_nodes + s.trace.tri_tests) as f64)
        .collect();
    let total_work: f64 = work.iter().sum();
    let measured: Vec<f64> = work
        .iter()
        .map(|w| {
            if total_work > 0.0 {
                w / total_work
            } else {
                0.0
            }
        })
        .collect();
    let mut totals = WorkerStats::default();
    let mut bytes = 0u64;
    for s in &stats {
        totals += s;
        bytes += s.peers.iter().map(|p| p.bytes_sent).sum::<u64>();
    }
    // Load is what each worker computed in the render phase: its CPU time
    // where it was counted (busy wall time would charge a worker for the
    // time another process held its core, as on any machine with fewer
    // cores than worker threads), else its busy time.
    let cpu: Vec<f64> = stats.iter().map(|s| s.cpu_s - s.setup_cpu_s).collect();
    let counted = cpu.iter().all(|&c| c > 0.0);
    let busy: Vec<f64> = if counted {
        cpu
    } else {
        stats.iter().map(|s| s.busy_s).collect()
    };
    let load_imbalance = max_over_mean(&busy);
    // With its setup, what the partition put on each worker.
    let total_imbalance = if counted {
        max_over_mean(&stats.iter().map(|s| s.cpu_s).collect::<Vec<_>>())
    } else {
        load_imbalance
    };
    let end = a.t_rendered.unwrap_or_else(Instant::now);
    let prepared = a.t_prepared.unwrap_or(a.started);
    let ready = a.t_ready.unwrap_or(end);
    let render_s = (end - a.t_first_tile.unwrap_or(end)).as_secs_f64();
    let t = &prep.timings;
    let samples = totals.trace.samples;
    // A correlation over workers says something about the partition only
    // over three or more, and only where the partition placed the work.
    let meaningful = measured.len() >= 3 && !prep.replicated;
    FarmReport {
        scene: j.req.name.clone(),
        width: j.req.camera.width,
        height: j.req.camera.height,
        spp: j.req.settings.spp,
        max_depth: j.req.settings.max_depth,
        seed: j.req.settings.seed,
        sampler: j.req.settings.sampler.name().into(),
        partitioner: format!("{:?}", j.req.options.partitioner),
        cost_model: cost_model_label(
            j.req.options.cost_model,
            prep.preview_rays,
            prep.small_preview,
        ),
        policy: j.req.options.fetch.name().to_string(),
        replicated: prep.replicated,
        bvh_quality: prep.bvh_quality,
        leaves: prep.leaves,
        triangles: prep.scene.tris.len() as u64,
        route_leaves: prep.map.route.leaves() as u32,
        shared_leaves: prep.shared_leaves.len() as u32,
        shared_refs: prep
            .shared_leaves
            .iter()
            .map(|&l| prep.leaf_tris[l as usize] as u64)
            .sum(),
        phases: Phases {
            load_s: j.req.load_s,
            prepare_s: (prepared - a.started).as_secs_f64(),
            octree_s: t.octree_s,
            preview_s: t.preview_s,
            partition_s: t.partition_s,
            distribution_s: ready.saturating_duration_since(prepared).as_secs_f64(),
            bvh_s: stats.iter().map(|s| s.bvh_build_s).fold(0.0, f64::max),
            layout_s: f64::from_bits(prep.layout_s.load(std::sync::atomic::Ordering::Relaxed)),
            render_s,
            total_s: j.started.elapsed().as_secs_f64(),
        },
        prediction: Prediction {
            analytic_r: meaningful.then(|| cost::correlation(&prep.analytic_share, &measured)),
            sampled_r: meaningful.then(|| cost::correlation(&prep.sampled_share, &measured)),
            preview_rays: prep.preview_rays,
            forwards_per_path: prep.forwards_per_path,
        },
        workers: stats
            .iter()
            .enumerate()
            .map(|(w, s)| WorkerSummary {
                id: w as u16,
                addr: names.get(w).cloned().unwrap_or_default(),
                predicted_cost_share: prep.predicted_share(w),
                measured_cost_share: measured[w],
                stats: s.clone(),
            })
            .collect(),
        load_imbalance,
        total_imbalance,
        forwarded_fraction: totals.forwarded_out as f64 / totals.trace.rays().max(1) as f64,
        bytes_per_sample: bytes as f64 / samples.max(1) as f64,
        samples_per_s: samples as f64 / render_s.max(1e-9),
        totals,
        recovery: j.recovery.clone(),
        irradiance: j.overture.as_ref().map(|o| o.report()),
        error_estimate: j.film.error_estimate(),
        target_rel_mse: j.req.settings.target_rel_mse,
        spp_rendered: j.film.spp_done(),
        sample_counts: j
            .film
            .sample_counts()
            .and_then(locus_core::report::SampleCounts::of),
    }
}

/// What the report says of the cost model: the one asked for, and for a
/// sampled one which preview the regions came from, or that none was
/// traced (a lone worker, or a job that holds the whole scene on every
/// worker, has no regions to draw and so traces none).
fn cost_model_label(asked: CostModel, preview_rays: u64, small_preview: bool) -> String {
    match (asked, preview_rays, small_preview) {
        (CostModel::Analytic, ..) => "Analytic".into(),
        (m, 0, _) => format!("{m:?} (no preview traced)"),
        (CostModel::Auto, _, true) => "Sampled (auto: the small preview)".into(),
        (CostModel::Auto, _, false) => "Sampled (auto)".into(),
        (m, ..) => format!("{m:?}"),
    }
}

/// The largest of `v` over their mean; 1 where there is nothing to share.
fn max_over_mean(v: &[f64]) -> f64 {
    let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
    let max = v.iter().cloned().fold(0.0, f64::max);
    if mean > 0.0 { max / mean } else { 1.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A job that traced no preview does not claim a sampled model; one
    /// that did says which preview.
    #[test]
    fn the_cost_model_says_whether_a_preview_was_traced() {
        let label = cost_model_label;
        assert_eq!(label(CostModel::Auto, 0, false), "Auto (no preview traced)");
        assert_eq!(
            label(CostModel::Sampled, 0, false),
            "Sampled (no preview traced)"
        );
        assert_eq!(label(CostModel::Auto, 5, false), "Sampled (auto)");
        assert_eq!(
            label(CostModel::Auto, 5, true),
            "Sampled (auto: the small preview)"
        );
        assert_eq!(label(CostModel::Small, 5, true), "Small");
        assert_eq!(label(CostModel::Sampled, 5, false), "Sampled");
        assert_eq!(label(CostModel::Analytic, 0, false), "Analytic");
    }
}
