//! Daemon configuration: a TOML file (see `configs/`), overridden by flags
//! and, for the token, the `LOCUS_TOKEN` environment variable.

use anyhow::{Context, bail};
use serde::Deserialize;
use std::path::{Path, PathBuf};

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub token: Option<String>,
    #[serde(default)]
    pub scheduler: SchedulerSection,
    #[serde(default)]
    pub worker: WorkerSection,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SchedulerSection {
    pub listen: Option<String>,
    pub max_queued_jobs: Option<usize>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorkerSection {
    pub scheduler: Option<String>,
    pub listen: Option<String>,
    pub advertise: Option<String>,
    pub threads: Option<usize>,
    pub memory_budget: Option<u64>,
    pub name: Option<String>,
}

impl Config {
    pub fn load(path: Option<&Path>) -> anyhow::Result<Self> {
        let Some(p) = path else {
            return Ok(Self::default());
        };
        let text =
            std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
        toml::from_str(&text).map_err(|e| {
            let line = e
                .span()
                .map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
            match line {
                Some(l) => anyhow::anyhow!("{}:{l}: {}", p.display(), e.message()),
                None => anyhow::anyhow!("{}: {}", p.display(), e.message()),
            }
        })
    }

    /// The cluster token: flag or `LOCUS_TOKEN` (clap merges those two)
    /// first, then the config file.
    pub fn token(&self, flag: Option<String>, config: Option<&PathBuf>) -> anyhow::Result<String> {
        match flag.or_else(|| self.token.clone()) {
            Some(t) if !t.is_empty() => Ok(t),
            _ => bail!(
                "no cluster token: pass --token, set LOCUS_TOKEN, or put `token = \"...\"` in {}",
                config.map_or("a --config file".to_string(), |p| p.display().to_string())
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn example_configs_parse() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
        let s = Config::load(Some(&dir.join("scheduler.toml"))).unwrap();
        assert!(s.scheduler.listen.is_some() && s.token.is_some());
        let w = Config::load(Some(&dir.join("worker.toml"))).unwrap();
        assert!(w.worker.scheduler.is_some() && w.worker.listen.is_some());
    }

    #[test]
    fn bad_config_names_file_and_line() {
        let p = std::env::temp_dir().join(format!("locus-bad-config-{}.toml", std::process::id()));
        std::fs::write(&p, "token = \"x\"\n[worker]\nthreds = 2\n").unwrap();
        let e = Config::load(Some(&p)).unwrap_err().to_string();
        assert!(e.contains(&format!("{}:3", p.display())), "{e}");
        let none = Config::default().token(None, None).unwrap_err().to_string();
        assert!(none.contains("LOCUS_TOKEN"));
    }
}
