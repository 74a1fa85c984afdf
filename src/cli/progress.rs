//! Progress bars on stderr for the long library calls (training, collection, evaluations).
use flowram::policy::training::trainer::{StepLoss, TrainProgress};
use flowram::rollout::collection::CollectProgress;
use flowram::rollout::evaluation::EvaluationProgress;
use indicatif::{ProgressBar, ProgressStyle};

fn bar(template: &str, len: u64) -> ProgressBar {
    let bar = ProgressBar::new(len);
    bar.set_style(ProgressStyle::with_template(template).unwrap_or_else(|_| ProgressStyle::default_bar()));
    bar
}

/// A progress bar over the episodes (or keyframes) of one task at a time.
pub struct TaskBar {
    bar: Option<ProgressBar>,
    unit: &'static str,
}

impl TaskBar {
    pub fn new(unit: &'static str) -> Self {
        Self { bar: None, unit }
    }

    /// A bar for collecting `episodes` successful episodes of `task`.
    pub fn for_collection(task: &str, episodes: usize) -> Self {
        let mut b = Self::new("episodes");
        b.started(task, episodes);
        b
    }

    /// Removes the bar.
    pub fn finish(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
    }

    /// Prints a line above the bar.
    pub fn println(&self, line: String) {
        match &self.bar {
            Some(bar) => bar.println(line),
            None => eprintln!("{line}"),
        }
    }
}

impl EvaluationProgress for TaskBar {
    fn started(&mut self, group: &str, total: usize) {
        let template = format!(
            "{{spinner}} {{msg}} [{{bar:30}}] {{pos}}/{{len}} {}, {{elapsed_precise}} (eta {{eta}})",
            self.unit
        );
        let b = bar(&template, total as u64);
        b.set_message(group.to_string());
        self.bar = Some(b);
    }

    fn advanced(&mut self, done: usize) {
        if let Some(b) = &self.bar {
            b.set_position(done as u64);
        }
    }

    fn finished(&mut self) {
        self.finish();
    }
}

impl CollectProgress for TaskBar {
    fn saved(&mut self, successes: usize) {
        self.advanced(successes);
    }

    fn failed(&mut self, seed: u64, reached: usize, keyframes: usize) {
        self.println(format!("seed {seed}: expert failed ({reached} keyframes reached of {keyframes}), not saved"));
    }
}

/// The training progress bar: step, loss, ETA.
pub struct TrainBar(pub ProgressBar);

impl TrainBar {
    pub fn new() -> Self {
        Self(bar("{spinner} [{bar:30}] step {pos}/{len} {msg}, {elapsed_precise} (eta {eta})", 0))
    }
}

impl TrainProgress for TrainBar {
    fn step(&mut self, step: u64, total: u64, loss: &StepLoss) {
        self.0.set_length(total);
        self.0.set_position(step);
        self.0.set_message(format!("loss {:.4} (cfm {:.4}, open {:.4})", loss.total, loss.cfm, loss.bce));
    }
}
