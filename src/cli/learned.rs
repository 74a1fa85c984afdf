//! The arguments of a learned policy acting closed loop (`run --policy flowram`,
//! `bench success`), and loading it.
use std::path::{Path, PathBuf};

use clap::Args;
use flowram::policy::config::{Consensus, PointerSharpening, PolicyConfig};
use flowram::policy::inference::{Policy, SamplingOptions};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::rollout::learned::{DEFAULT_CAMERAS, FlowRamActor};

/// The position pointer's sampling options (`flow.pointer_sharpening`; README, "Inference"),
/// shared by every command that samples a checkpoint: each, when given, replaces the
/// checkpoint's setting.
#[derive(Debug, Args)]
pub struct SharpeningArgs {
    /// The position pointer's temperature over the first Euler steps (those at flow time below
    /// the checkpoint's flow.pointer_sharpening.until, 0.5 by default); 1: as trained (default:
    /// the checkpoint's flow.pointer_sharpening.temperature).
    #[arg(long, value_parser = super::positive_number)]
    pub pointer_temperature: Option<f64>,
    /// The position pointer as the posterior given the noisy position at every Euler step
    /// (`flow.pointer_sharpening.posterior`); default: the checkpoint's.
    #[arg(long)]
    pub pointer_posterior: bool,
    /// m: the posterior's candidate width (`flow.pointer_sharpening.posterior_width`; turns the
    /// posterior on); default: the checkpoint's.
    #[arg(long, value_parser = super::non_negative_number)]
    pub pointer_posterior_width: Option<f64>,
    /// The instruction's classifier-free guidance of the position pointer, w: its scores are
    /// s_null + w (s - s_null) against the null instruction's
    /// (`flow.pointer_sharpening.guidance`; 1: as trained; for checkpoints trained with
    /// flow.instruction_dropout); default: the checkpoint's.
    #[arg(long, value_parser = super::non_negative_number)]
    pub pointer_guidance: Option<f64>,
}

impl SharpeningArgs {
    /// The checkpoint's `flow.pointer_sharpening` with what the command line gave in its place.
    /// Warns (stderr) when the instruction's guidance is asked of a checkpoint trained without
    /// `flow.instruction_dropout`, which never saw the null instruction it contrasts with.
    pub fn over(&self, config: &PolicyConfig) -> PointerSharpening {
        let sharpening = config
            .flow
            .pointer_sharpening
            .with_temperature(self.pointer_temperature)
            .with_posterior(self.pointer_posterior)
            .with_posterior_width(self.pointer_posterior_width)
            .with_guidance(self.pointer_guidance);
        if sharpening.guided() && config.flow.instruction_dropout == 0.0 {
            eprintln!(
                "warning: --pointer-guidance {} on a checkpoint trained without flow.instruction_dropout: it never saw \
                 the null instruction the guidance contrasts with",
                sharpening.guidance
            );
        }
        sharpening
    }
}

/// How a learned policy runs closed loop.
#[derive(Debug, Args)]
pub struct LearnedArgs {
    /// Run folder (runs/NAME) or checkpoint folder of a trained policy [default: the shipped
    /// checkpoint for the task: models/policy/pretrained/five-tasks for open_drawer,
    /// push_buttons, slide_block, close_jar and stack_blocks, ten-tasks for the others].
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Euler steps (default: the checkpoint's flow.sampling_steps).
    #[arg(long, value_parser = super::at_least_one)]
    pub steps: Option<usize>,
    /// Keyframe samples per observation, the executed one their consensus (default: the
    /// checkpoint's flow.consensus_samples).
    #[arg(long, value_parser = super::at_least_one)]
    pub samples: Option<usize>,
    /// Which sample is executed: medoid (least summed distance to the others) or mode (most
    /// others within 2 cm) (default: the checkpoint's flow.consensus).
    #[arg(long, value_parser = super::consensus_rule)]
    pub consensus: Option<Consensus>,
    #[command(flatten)]
    pub sharpening: SharpeningArgs,
    /// Global geometric tokens at every step (the w/o-DRS ablation).
    #[arg(long)]
    pub no_drs: bool,
    /// Stop after this many predicted keyframes if the task has not succeeded (25: RLBench's
    /// evaluation limit, which 3D Diffuser Actor and FlowRAM use; stack_blocks' expert needs six
    /// per block, 12-24).
    #[arg(long, default_value_t = 25)]
    pub max_keyframes: usize,
    /// Cameras the policy sees, in the training datasets' order.
    #[arg(long, value_delimiter = ',', default_values_t = DEFAULT_CAMERAS.map(String::from))]
    pub cameras: Vec<String>,
}

impl LearnedArgs {
    /// Loads the checkpoint (`--checkpoint`, else the shipped one for `tasks`), with the sampling
    /// options.
    pub fn load_actor(&self, tasks: &[&str]) -> anyhow::Result<FlowRamActor> {
        let checkpoint = match &self.checkpoint {
            Some(path) => path.clone(),
            None => {
                let shipped = shipped_checkpoint(tasks);
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
            samples: self.samples.unwrap_or(policy.config().flow.consensus_samples),
            drs: !self.no_drs,
            seed: 0,
            consensus: self.consensus.unwrap_or(policy.config().flow.consensus),
            sharpening: self.sharpening.over(policy.config()),
        };
        Ok(FlowRamActor::new(policy, options))
    }
}

/// The checkpoints shipped in `models/policy/pretrained/` with the tasks each was trained on
/// (`None`: every task), in order of preference. The five-task one succeeds more often on its
/// five tasks (both model cards); the ten-task one is the only one that knows the other five.
const SHIPPED: [(&str, Option<&[&str]>); 2] = [
    ("five-tasks", Some(&["open_drawer", "push_buttons", "slide_block", "close_jar", "stack_blocks"])),
    ("ten-tasks", None),
];

/// The shipped checkpoint for a run of `tasks`: the first of [`SHIPPED`] trained on all of them.
pub fn shipped_checkpoint(tasks: &[&str]) -> PathBuf {
    let name = SHIPPED
        .iter()
        .find(|(_, trained)| trained.is_none_or(|trained| tasks.iter().all(|task| trained.contains(task))))
        .map_or("ten-tasks", |(name, _)| name);
    flowram::deps::models_dir().join("policy/pretrained").join(name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_gets_the_shipped_checkpoint_trained_on_all_its_tasks() {
        let name = |tasks: &[&str]| shipped_checkpoint(tasks).file_name().unwrap().to_string_lossy().into_owned();
        assert_eq!(name(&["push_buttons"]), "five-tasks");
        assert_eq!(name(&["open_drawer", "stack_blocks"]), "five-tasks");
        assert_eq!(name(&["turn_tap"]), "ten-tasks");
        assert_eq!(name(&["open_drawer", "turn_tap"]), "ten-tasks");
        for (name, _) in SHIPPED {
            assert!(flowram::deps::models_dir().join("policy/pretrained").join(name).join("config.json").is_file());
        }
    }
}
