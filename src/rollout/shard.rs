//! Splitting seeded work (demonstration collection, closed-loop evaluation) over processes or
//! machines: shard `i` of `n` owns the items (episode slots) `k` with `k mod n == i`, so the
//! shards' seed sets are disjoint and their union is what one unsharded run does.
//!
//! The shard comes from `--shard-index` / `--shard-count`, else from the scheduler's
//! environment:
//! - Slurm job arrays: `SLURM_ARRAY_TASK_ID` (minus `SLURM_ARRAY_TASK_MIN`, divided by
//!   `SLURM_ARRAY_TASK_STEP`) of `SLURM_ARRAY_TASK_COUNT`;
//! - Kubernetes Indexed Jobs: `JOB_COMPLETION_INDEX`, with the count from `--shard-count` (a Job
//!   does not export its completions).
//!
//! Each shard writes its own output with a manifest (`collection::CollectionManifest`,
//! `evaluation::SuccessRecord`) and `flowram merge` combines them; see `docs/scale-out.md`.
use serde::{Deserialize, Serialize};

/// One shard of `count`: the items `k` with `k % count == index`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

/// A shard that cannot be resolved from the arguments and the environment.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ShardError {
    #[error("shard index {index} is out of range for {count} shards: expected 0 <= --shard-index < --shard-count")]
    OutOfRange { index: usize, count: usize },
    #[error("--shard-count must be at least 1")]
    ZeroCount,
    #[error("--shard-index needs --shard-count (how many shards the work is split into)")]
    IndexWithoutCount,
    #[error("--shard-count needs --shard-index (or a scheduler's index: SLURM_ARRAY_TASK_ID, JOB_COMPLETION_INDEX)")]
    CountWithoutIndex,
    #[error(
        "{variable} is set (a Kubernetes Indexed Job), but not the shard count: pass --shard-count equal to the Job's `completions`"
    )]
    EnvWithoutCount { variable: &'static str },
    #[error("environment variable {variable}={value:?} is not a non-negative integer; {hint}")]
    BadEnv { variable: &'static str, value: String, hint: &'static str },
    #[error("--shard-count {flag} disagrees with the scheduler's {variable}={env}; drop the flag or make them equal")]
    CountDisagrees { flag: usize, variable: &'static str, env: usize },
}

impl Shard {
    /// The whole work in one process.
    pub const WHOLE: Shard = Shard { index: 0, count: 1 };

    pub fn new(index: usize, count: usize) -> Result<Self, ShardError> {
        if count == 0 {
            return Err(ShardError::ZeroCount);
        }
        if index >= count {
            return Err(ShardError::OutOfRange { index, count });
        }
        Ok(Self { index, count })
    }

    /// Whether this shard owns item (episode slot) `k`.
    pub fn owns(&self, k: usize) -> bool {
        k % self.count == self.index
    }

    /// The items of `0..total` this shard owns, in order.
    pub fn items(&self, total: usize) -> impl Iterator<Item = usize> + use<> {
        (self.index..total).step_by(self.count)
    }

    pub fn is_whole(&self) -> bool {
        self.count == 1
    }

    /// The shard from the flags, else from the scheduler's environment (see the module docs),
    /// else [`Shard::WHOLE`]. `env` reads an environment variable (`std::env::var(..).ok()` in
    /// the CLI; a map in tests).
    pub fn resolve(
        index: Option<usize>,
        count: Option<usize>,
        env: &dyn Fn(&str) -> Option<String>,
    ) -> Result<Self, ShardError> {
        if let Some(index) = index {
            return Self::new(index, count.ok_or(ShardError::IndexWithoutCount)?);
        }
        let number = |variable: &'static str, hint: &'static str| -> Result<Option<usize>, ShardError> {
            match env(variable) {
                None => Ok(None),
                Some(value) => value.trim().parse().map(Some).map_err(|_| ShardError::BadEnv { variable, value, hint }),
            }
        };
        const SLURM: &str = "set by Slurm for `sbatch --array`";
        if let Some(id) = number("SLURM_ARRAY_TASK_ID", SLURM)? {
            let min = number("SLURM_ARRAY_TASK_MIN", SLURM)?.unwrap_or(0);
            let step = number("SLURM_ARRAY_TASK_STEP", SLURM)?.unwrap_or(1).max(1);
            let env_count = number("SLURM_ARRAY_TASK_COUNT", SLURM)?;
            let count = match (count, env_count) {
                (Some(flag), Some(env)) if flag != env => {
                    return Err(ShardError::CountDisagrees { flag, variable: "SLURM_ARRAY_TASK_COUNT", env });
                }
                (Some(c), _) | (None, Some(c)) => c,
                (None, None) => return Err(ShardError::IndexWithoutCount),
            };
            let offset = id.checked_sub(min).ok_or(ShardError::OutOfRange { index: id, count })?;
            return Self::new(offset / step, count);
        }
        const K8S: &str = "set by Kubernetes for Jobs with completionMode: Indexed";
        if let Some(index) = number("JOB_COMPLETION_INDEX", K8S)? {
            let count = count.ok_or(ShardError::EnvWithoutCount { variable: "JOB_COMPLETION_INDEX" })?;
            return Self::new(index, count);
        }
        match count {
            None | Some(1) => Ok(Self::WHOLE),
            Some(_) => Err(ShardError::CountWithoutIndex),
        }
    }
}

/// Checks that the `shards` of one piece of work (each with the name of its output, for the
/// messages) are every shard `0..count` of one count exactly once; what a merge needs. The
/// error says which shard is doubled, missing or of another count.
pub fn check_shard_set(shards: &[(Shard, String)]) -> Result<(), String> {
    let Some((first, first_name)) = shards.first() else { return Err("no shard outputs given".into()) };
    let mut seen = vec![false; first.count];
    for (shard, name) in shards {
        if shard.count != first.count {
            return Err(format!(
                "{name} is shard {} of {} but {first_name} is one of {}",
                shard.index, shard.count, first.count
            ));
        }
        if std::mem::replace(&mut seen[shard.index], true) {
            return Err(format!("shard {} of {} is given twice (again in {name})", shard.index, shard.count));
        }
    }
    let missing: Vec<usize> = (0..first.count).filter(|&i| !seen[i]).collect();
    if !missing.is_empty() {
        return Err(format!(
            "shards {missing:?} of {} are missing; run them and merge all {}",
            first.count, first.count
        ));
    }
    Ok(())
}

/// The source revision of this build's tree (`git describe --always --dirty` in the folder the
/// crate was built from), or `"unknown"` when that is not a git checkout any more (a binary
/// copied to a cluster). Recorded in the manifests so that shards of different code are seen.
pub fn source_revision() -> String {
    let dir = env!("CARGO_MANIFEST_DIR");
    std::process::Command::new("git")
        .args(["-C", dir, "describe", "--always", "--dirty", "--abbrev=12"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "unknown".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env_of(pairs: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
        let pairs: Vec<(String, String)> = pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        move |k: &str| pairs.iter().find(|(key, _)| key == k).map(|(_, v)| v.clone())
    }

    #[test]
    fn shards_partition_the_items() {
        let n = 3;
        let mut seen = [0; 10];
        for i in 0..n {
            for k in Shard::new(i, n).unwrap().items(10) {
                seen[k] += 1;
                assert!(Shard::new(i, n).unwrap().owns(k));
            }
        }
        assert!(seen.iter().all(|&c| c == 1));
    }

    #[test]
    fn flags_then_slurm_then_kubernetes() {
        let none = env_of(&[]);
        assert_eq!(Shard::resolve(None, None, &none), Ok(Shard::WHOLE));
        assert_eq!(Shard::resolve(Some(2), Some(3), &none), Ok(Shard { index: 2, count: 3 }));
        assert_eq!(Shard::resolve(Some(3), Some(3), &none), Err(ShardError::OutOfRange { index: 3, count: 3 }));
        assert_eq!(Shard::resolve(Some(0), None, &none), Err(ShardError::IndexWithoutCount));
        assert_eq!(Shard::resolve(None, Some(3), &none), Err(ShardError::CountWithoutIndex));
        assert_eq!(Shard::resolve(None, Some(1), &none), Ok(Shard::WHOLE));
        let slurm =
            env_of(&[("SLURM_ARRAY_TASK_ID", "5"), ("SLURM_ARRAY_TASK_MIN", "4"), ("SLURM_ARRAY_TASK_COUNT", "3")]);
        assert_eq!(Shard::resolve(None, None, &slurm), Ok(Shard { index: 1, count: 3 }));
        assert!(matches!(Shard::resolve(None, Some(4), &slurm), Err(ShardError::CountDisagrees { .. })));
        let stepped = env_of(&[
            ("SLURM_ARRAY_TASK_ID", "4"),
            ("SLURM_ARRAY_TASK_MIN", "0"),
            ("SLURM_ARRAY_TASK_STEP", "2"),
            ("SLURM_ARRAY_TASK_COUNT", "3"),
        ]);
        assert_eq!(Shard::resolve(None, None, &stepped), Ok(Shard { index: 2, count: 3 }));
        let k8s = env_of(&[("JOB_COMPLETION_INDEX", "1")]);
        assert_eq!(Shard::resolve(None, Some(2), &k8s), Ok(Shard { index: 1, count: 2 }));
        let err = Shard::resolve(None, None, &k8s).unwrap_err();
        assert!(err.to_string().contains("--shard-count"), "{err}");
        let bad = env_of(&[("JOB_COMPLETION_INDEX", "x")]);
        assert!(matches!(Shard::resolve(None, Some(2), &bad), Err(ShardError::BadEnv { .. })));
        // The flags win over the environment.
        assert_eq!(Shard::resolve(Some(0), Some(2), &slurm), Ok(Shard { index: 0, count: 2 }));
    }
}
