//! `locus bench-farm`'s tables: its rows as Markdown, the cost
//! prediction's quality, and the check that every farm image matched one
//! machine's.

use super::farm::{Prediction, Row};
use anyhow::{Result, bail};
use std::fmt::Write as _;

fn mib(b: u64) -> String {
    format!("{:.0}", b as f64 / (1 << 20) as f64)
}

/// The rows as Markdown tables: the farm against one machine, and the
/// partitions under `forward`.
pub fn markdown(rows: &[Row]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| scene | configuration | render s | total s | efficiency (render) | efficiency (total) | CPU us / forward | a forward in rays' CPU | CPU us / ray (one machine) | CPU us / ray above one machine | forwards / ray | bytes / sample | items / message | imbalance | imbalance with setup | idle | engine busy | handed | peak MiB per process (budget) | bit-identical |"
    );
    let _ = writeln!(
        s,
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"
    );
    for r in rows {
        let peaks = r
            .peak_rss
            .iter()
            .map(|&b| mib(b))
            .collect::<Vec<_>>()
            .join(" ");
        let budget = if r.budget > 0 {
            format!(" ({})", mib(r.budget))
        } else {
            String::new()
        };
        let _ = writeln!(
            s,
            "| {} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {} | {} | {} | {} | {:.3} | {:.0} | {} | {:.2} | {:.2} | {:.0}% | {} | {} | {}{} | {} |",
            r.scene,
            r.config,
            r.render_s,
            r.total_s,
            r.efficiency_render,
            r.efficiency_total,
            r.us_per_forward.map_or("".into(), |u| format!("{u:.2}")),
            r.forward_in_rays.map_or("".into(), |u| format!("{u:.2}")),
            r.us_per_ray.map_or("".into(), |u| format!("{u:.3}")),
            r.us_extra_per_ray.map_or("".into(), |u| format!("{u:.3}")),
            r.forwards_per_ray,
            r.bytes_per_sample,
            r.items_per_message.map_or("".into(), |m| format!("{m:.0}")),
            r.imbalance,
            r.total_imbalance,
            r.idle_share * 100.0,
            r.engine_busy
                .map_or("".into(), |b| format!("{:.0}%", b * 100.0)),
            r.handed,
            peaks,
            budget,
            if r.identical { "yes" } else { "NO" }
        );
    }
    s
}

/// The prediction quality as a Markdown table.
pub fn prediction_markdown(p: &[Prediction]) -> String {
    let mut s = String::from(
        "| scene | leaves | r analytic vs measured | r sampled vs measured | sampled rays | measured rays | BVH steps a ray, leaf by leaf | BVH steps a ray, render |\n|---|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for q in p {
        let _ = writeln!(
            s,
            "| {} | {} | {:.3} | {:.3} | {} | {} | {:.1} | {:.1} |",
            q.scene,
            q.leaves,
            q.analytic_r,
            q.sampled_r,
            q.sampled_rays,
            q.measured_rays,
            q.preview_steps_per_ray,
            q.render_steps_per_ray
        );
    }
    s
}

/// Fails when any farm image differs from one machine's.
pub fn check(rows: &[Row]) -> Result<()> {
    if let Some(r) = rows.iter().find(|r| !r.identical) {
        bail!(
            "{} {}: the farm's image differs from one machine's",
            r.scene,
            r.config
        );
    }
    Ok(())
}
