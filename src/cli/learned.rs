//! The arguments of a learned policy acting closed loop (`run --policy flowram`,
//! `bench success`), and loading it.
use std::path::{Path, PathBuf};

use clap::Args;
use flowram::policy::inference::{Policy, SamplingOptions};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::rollout::learned::{DEFAULT_CAMERAS, FlowRamActor};

/// How a learned policy runs closed loop.
#[derive(Debug, Args)]
pub struct LearnedArgs {
    /// Run folder (runs/NAME) or checkpoint folder of a trained policy [default: the checkpoint
    /// shipped in models/policy/pretrained/ten-tasks; five-tasks is beside it].
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Euler steps (default: the checkpoint's flow.sampling_steps).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Global geometric tokens at every step (the w/o-DRS ablation).
    #[arg(long)]
    pub no_drs: bool,
    /// Stop after this many predicted keyframes if the task has not succeeded (25: RLBench's
    /// evaluation limit, which 3D Diffuser Actor and FlowRAM use; stack_blocks' expert needs 17).
    #[arg(long, default_value_t = 25)]
    pub max_keyframes: usize,
    /// Cameras the policy sees, in the training datasets' order.
    #[arg(long, value_delimiter = ',', default_values_t = DEFAULT_CAMERAS.map(String::from))]
    pub cameras: Vec<String>,
}

impl LearnedArgs {
    /// Loads the checkpoint (`--checkpoint`, else the shipped one), with the sampling options.
    pub fn load_actor(&self) -> anyhow::Result<FlowRamActor> {
        let checkpoint = match &self.checkpoint {
            Some(path) => path.clone(),
            None => {
                let shipped = shipped_checkpoint();
                anyhow::ensure!(
                    shipped.is_dir(),
                    "no --checkpoint given and the shipped checkpoint {} is missing: pass --checkpoint runs/NAME \
                     (a run folder from `flowram train`)",
                    shipped.display()
                );
                shipped
            }
        };
        self.load_actor_from(&checkpoint)
    }

    /// Loads `checkpoint` with these sampling options.
    pub fn load_actor_from(&self, checkpoint: &Path) -> anyhow::Result<FlowRamActor> {
        anyhow::ensure!(self.max_keyframes > 0, "--max-keyframes must be at least 1");
        let policy = Policy::load(checkpoint, TextEncoder::load_installed()?)?;
        let options = SamplingOptions {
            steps: self.steps.unwrap_or(policy.config().flow.sampling_steps),
            samples: 1,
            drs: !self.no_drs,
            seed: 0,
        };
        Ok(FlowRamActor::new(policy, options))
    }
}

/// The five-task checkpoint shipped with the project (see its model card).
pub fn shipped_checkpoint() -> PathBuf {
    flowram::deps::models_dir().join("policy/pretrained/ten-tasks")
}
