//! The FlowRAM policy end to end on real demonstrations (rendered by the real simulator): it can
//! overfit a handful of keyframes, checkpoints round-trip, bad checkpoints are named.
use std::sync::OnceLock;

use flowram::data::Episode;
use flowram::policy::PolicyError;
use flowram::policy::config::{
    Consensus, InstructionPooling, LanguageReads, PointerSharpening, PointerTarget, PolicyConfig,
};
use flowram::policy::inference::{Policy, SamplingOptions};
use flowram::policy::network::text_encoder::TextEncoder;
use flowram::policy::scene::observation::Observation;
use flowram::policy::training::data::TrainingData;
use flowram::policy::training::trainer::{StepLoss, TrainProgress, Trainer, train};
use flowram::rollout::collection;
use flowram::sim::Visuals;
use flowram::tasks;

fn text() -> TextEncoder {
    // the binary's allocator settings (training steps twice as fast; see policy::runtime)
    flowram::policy::runtime::configure_malloc();
    TextEncoder::load_installed().unwrap()
}

/// One push_buttons demonstration (front and wrist cameras, 64 px), rendered once.
fn demonstration() -> &'static Episode {
    static EPISODE: OnceLock<Episode> = OnceLock::new();
    EPISODE.get_or_init(|| {
        let task = tasks::by_name("push_buttons").unwrap();
        let episode =
            collection::demonstration(task.as_ref(), 0, 0, &["front", "left_shoulder"], 64, Visuals::Fast).unwrap();
        assert!(episode.success);
        episode
    })
}

/// The CPU config shrunk to test size: 64 px, few tokens, one layer, a fast learning rate.
fn tiny_config() -> PolicyConfig {
    let mut c = PolicyConfig::cpu_default().unwrap();
    c.observation.image_size = 64;
    // push_buttons' part of the table: a tighter box makes a normalised error fewer millimetres.
    c.observation.workspace =
        flowram::policy::scene::workspace::WorkspaceBounds::new([0.15, -0.35, 0.74], [0.85, 0.35, 1.14]).unwrap();
    c.observation.semantic_tokens = 128;
    c.observation.geometric_tokens = 32;
    c.observation.min_inside = 8;
    c.model.layers = 2;
    c.train.batch = 16;
    c.train.learning_rate = 2e-3;
    c.train.warmup_steps = 20;
    c.train.cosine_decay = true;
    c.train.min_learning_rate = 1e-5;
    c.train.steps = OVERFIT_STEPS;
    c.train.weight_decay = 0.0;
    c.train.ema_decay = 0.9;
    c.train.translation_jitter = 0.0;
    c.train.brightness_jitter = 0.0;
    c.train.log_every = 10;
    c.train.checkpoint_every = 1000;
    c.validate().unwrap();
    c
}

/// Steps of the overfitting test (the cosine decay ends there); about 5 min on 2 cores.
const OVERFIT_STEPS: usize = 1500;

struct Quiet;
impl TrainProgress for Quiet {
    fn step(&mut self, _: u64, _: u64, _: &StepLoss) {}
}

#[test]
fn overfits_a_handful_of_keyframes() {
    let episode = demonstration().clone();
    let keyframes = episode.keyframes();
    let mut data = TrainingData::from_episodes(vec![episode.clone()]).unwrap();
    let mut text = text();
    let mut trainer = Trainer::new(&tiny_config()).unwrap();
    let mut losses = Vec::new();
    for _ in 0..OVERFIT_STEPS {
        losses.push(trainer.train_step(&mut data, &mut text).unwrap().total);
    }
    let first: f64 = losses[..20].iter().sum::<f64>() / 20.0;
    let last: f64 = losses[losses.len() - 20..].iter().sum::<f64>() / 20.0;
    assert!(last * 10.0 <= first, "loss fell only from {first:.4} to {last:.4}");
    // Sample with the EMA weights, through a saved checkpoint.
    let dir = tempfile::tempdir().unwrap();
    trainer.save(dir.path(), None).unwrap();
    let mut policy = Policy::load(dir.path(), text).unwrap();
    for k in 0..keyframes {
        let observation = Observation::from_episode(&episode, k).unwrap();
        let target = Observation::episode_action(&episode, k);
        let predicted = policy.predict(&observation, &SamplingOptions::new(8, 1, 0)).unwrap()[0];
        let (p, r) = predicted.error_to(&target);
        assert!(p < 0.01 && r < 5f32.to_radians(), "keyframe {k}: {:.1} mm, {:.1} deg off", p * 1e3, r.to_degrees());
        assert_eq!(predicted.gripper_open, target.gripper_open, "keyframe {k}");
    }
}

#[test]
fn checkpoint_round_trip_and_truncation() {
    let episode = demonstration().clone();
    let mut data = TrainingData::from_episodes(vec![episode.clone()]).unwrap();
    let run = tempfile::tempdir().unwrap();
    let mut config = tiny_config();
    config.train.steps = 3;
    config.train.checkpoint_every = 3;
    let mut text = text();
    train(run.path(), Some(&config), &mut data, &mut text, false, None, &mut Quiet).unwrap();
    let observation = Observation::from_episode(&episode, 1).unwrap();
    let options = SamplingOptions::new(4, 2, 7);
    let a = Policy::load(run.path(), text).unwrap().predict_once(&observation, &options);
    let b = Policy::load(run.path(), self::text()).unwrap().predict_once(&observation, &options);
    assert_eq!(a, b, "same checkpoint and noise seed, same prediction");
    let other = Policy::load(run.path(), self::text())
        .unwrap()
        .predict_once(&observation, &SamplingOptions { seed: 8, ..options });
    assert_ne!(a, other, "another noise seed gives other samples");

    // A new run refuses to overwrite, and a truncated checkpoint is named.
    // (a typed error: the CLI words it with its flags, --resume or another --out)
    let err = train(run.path(), Some(&config), &mut data, &mut self::text(), false, None, &mut Quiet).err().unwrap();
    assert!(matches!(err, PolicyError::RunHasCheckpoints { .. }), "{err}");
    assert!(err.to_string().contains("already has checkpoints"), "{err}");
    let step = run.path().join("checkpoints/step-000000003");
    let model = step.join("ema.safetensors");
    let bytes = std::fs::read(&model).unwrap();
    std::fs::write(&model, &bytes[..bytes.len() / 2]).unwrap();
    let err = Policy::load(run.path(), self::text()).err().unwrap().to_string();
    assert!(err.contains("ema.safetensors"), "{err}");
}

#[test]
fn resume_continues_exactly() {
    let episode = demonstration().clone();
    let mut config = tiny_config();
    config.train.steps = 4;
    config.train.checkpoint_every = 2;
    config.train.log_every = 1;
    let straight = tempfile::tempdir().unwrap();
    let resumed = tempfile::tempdir().unwrap();
    let mut data = TrainingData::from_episodes(vec![episode]).unwrap();
    train(straight.path(), Some(&config), &mut data, &mut text(), false, None, &mut Quiet).unwrap();
    // "Killed" after step 2 (its checkpoint), then resumed to 4.
    train(resumed.path(), Some(&config), &mut data, &mut text(), false, Some(2), &mut Quiet).unwrap();
    train(resumed.path(), None, &mut data, &mut text(), true, Some(4), &mut Quiet).unwrap();
    let read = |dir: &std::path::Path| std::fs::read(dir.join("checkpoints/step-000000004/model.safetensors")).unwrap();
    assert!(read(straight.path()) == read(resumed.path()), "resumed weights differ from the uninterrupted run's");
    let metrics = |dir: &std::path::Path| std::fs::read_to_string(dir.join("metrics.csv")).unwrap().lines().count();
    assert_eq!(metrics(straight.path()), metrics(resumed.path()));
}

trait PredictOnce {
    fn predict_once(self, observation: &Observation, options: &SamplingOptions) -> Vec<[f32; 7]>;
}

impl PredictOnce for Policy {
    fn predict_once(mut self, observation: &Observation, options: &SamplingOptions) -> Vec<[f32; 7]> {
        self.predict(observation, options)
            .unwrap()
            .iter()
            .map(|k| {
                [
                    k.position[0],
                    k.position[1],
                    k.position[2],
                    k.quat_wxyz[0],
                    k.quat_wxyz[1],
                    k.quat_wxyz[2],
                    k.quat_wxyz[3],
                ]
            })
            .collect()
    }
}

#[test]
fn the_instruction_reaches_the_adaln_condition_only_when_configured() {
    let episode = demonstration();
    let observation = Observation::from_episode(episode, 0).unwrap();
    let other = Observation { instruction: "open the middle drawer".into(), ..observation.clone() };
    assert_ne!(other.instruction, observation.instruction);
    let pooled = |adaln: bool, pooling: InstructionPooling, o: &Observation| -> Vec<f32> {
        let mut config = tiny_config();
        config.model.instruction_adaln = adaln;
        config.model.instruction_pooling = pooling;
        let mut policy = Policy::random(&config, text()).unwrap();
        let prepared = policy.prepare(o).unwrap();
        policy.encode(&prepared).unwrap().condition.flatten_all().unwrap().to_vec1().unwrap()
    };
    let condition = |adaln: bool, o: &Observation| -> Vec<f32> { pooled(adaln, InstructionPooling::Sentence, o) };
    // The paper's conditioning: proprioception only, whatever the instruction says.
    assert_eq!(condition(false, &observation), condition(false, &other));
    // With model.instruction_adaln, every block's modulation depends on the instruction.
    assert_ne!(condition(true, &observation), condition(true, &other));
    // ... also when it pools the instruction's tokens by attention; and pooling is not ignored.
    let attention = pooled(true, InstructionPooling::Attention, &observation);
    assert_ne!(attention, pooled(true, InstructionPooling::Attention, &other));
    assert_ne!(attention, condition(true, &observation));
    // Padding carries no weight: the same instruction padded to more tokens pools the same.
    let mut config = tiny_config();
    config.model.instruction_adaln = true;
    config.model.instruction_pooling = InstructionPooling::Attention;
    let mut longer = config.clone();
    longer.observation.language_tokens += 8;
    let at = |config: &PolicyConfig| -> Vec<f32> {
        let mut policy = Policy::random(config, text()).unwrap();
        let prepared = policy.prepare(&observation).unwrap();
        policy.encode(&prepared).unwrap().condition.flatten_all().unwrap().to_vec1().unwrap()
    };
    let (short, long) = (at(&config), at(&longer));
    assert!(short.iter().zip(&long).all(|(a, b)| (a - b).abs() < 1e-5), "padding changed the pooled instruction");
}

#[test]
fn the_instruction_pointer_reads_the_instruction_and_caches_like_the_rest_of_the_prefix() {
    use flowram::policy::inputs::{Augmentation, prefix_inputs, suffix_inputs};
    let mut config = tiny_config();
    // no AdaLN: the pointer token is the instruction's only way past the scan's first tokens
    config.model.instruction_adaln = false;
    config.model.instruction_pointer = true;
    // and no position pointer: this test also covers the cached path of the paper's readout
    config.model.position_pointer = false;
    config.flow.pointer_weight = 0.0;
    config.model.instruction_pooling = InstructionPooling::Attention;
    let mut policy = Policy::random(&config, text()).unwrap();
    let observation = Observation::from_episode(demonstration(), 0).unwrap();
    let prepared = policy.prepare(&observation).unwrap();
    let observations = [(&prepared, Augmentation::NONE)];
    let prefix = prefix_inputs(&config, &observations).unwrap();
    let action = [[0.1f32, -0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]];
    let suffix = suffix_inputs(&config, &observations, &[0], &action, &[0.4], &config.radius_schedule).unwrap();
    let out = policy.model.forward(&prefix, &suffix).unwrap();
    let goal = out.goal.expect("the training forward returns the instruction pointer's attention");
    assert_eq!(goal.dims(), &[1, config.observation.semantic_tokens]);
    let total: f32 = goal.exp().unwrap().sum_all().unwrap().to_scalar().unwrap();
    assert!((total - 1.0).abs() < 1e-4, "the attention sums to {total}");
    let whole = out.velocity.to_vec2::<f32>().unwrap();
    let encoded = policy.model.encode(&prefix).unwrap();
    let cached = policy.model.step(&encoded, &suffix).unwrap().velocity.to_vec2::<f32>().unwrap();
    for (a, b) in whole[0].iter().zip(&cached[0]) {
        assert!((a - b).abs() < 1e-4, "training forward {:?}, cached inference {:?}", whole[0], cached[0]);
    }
    // The pointer token itself (the prefix's last) moves with the instruction.
    let pointer_token = |o: &Observation| -> Vec<f32> {
        let mut policy = Policy::random(&config, text()).unwrap();
        let prepared = policy.prepare(o).unwrap();
        let prefix = prefix_inputs(&config, &[(&prepared, Augmentation::NONE)]).unwrap();
        let expected = config.observation.language_tokens + config.observation.semantic_tokens + 1;
        let tokens = policy.model.prefix_token_features(&prefix).unwrap();
        assert_eq!(tokens.dim(1).unwrap(), expected, "language, semantic, pointer");
        tokens.narrow(1, expected - 1, 1).unwrap().flatten_all().unwrap().to_vec1().unwrap()
    };
    let other = Observation { instruction: "open the middle drawer".into(), ..observation.clone() };
    assert_ne!(other.instruction, observation.instruction);
    assert_ne!(pointer_token(&observation), pointer_token(&other), "the pointer token does not read the instruction");
}

#[test]
fn the_goal_loss_points_the_instruction_pointer_at_the_episodes_last_keyframe() {
    use flowram::policy::inputs::{Augmentation, prefix_inputs};
    let mut config = tiny_config();
    config.model.instruction_pointer = true;
    config.train.batch = 8;
    let mut wrong = config.clone();
    wrong.model.instruction_pointer = false;
    wrong.flow.goal_weight = 1.0;
    let err = wrong.validate().unwrap_err().to_string();
    assert!(err.contains("flow.goal_weight") && err.contains("instruction_pointer"), "{err}");
    let episode = demonstration();
    let last =
        Observation::episode_action(episode, episode.keyframes() - 1).to_action(&config.observation.workspace).unwrap();
    // Mean distance (normalised units) from the pointed position to the last keyframe over the
    // episode's observations, after the same 100 steps with and without the goal loss.
    let pointing = |goal_weight: f64| -> f32 {
        let mut config = config.clone();
        config.flow.goal_weight = goal_weight;
        let mut data = TrainingData::from_episodes(vec![episode.clone()]).unwrap();
        let mut text = text();
        let mut trainer = Trainer::new(&config).unwrap();
        for _ in 0..100 {
            trainer.train_step(&mut data, &mut text).unwrap();
        }
        let mut policy = Policy::random(&config, text).unwrap();
        let mut total = 0.0;
        for k in 0..episode.keyframes() {
            let prepared = policy.prepare(&Observation::from_episode(episode, k).unwrap()).unwrap();
            let prefix = prefix_inputs(&config, &[(&prepared, Augmentation::NONE)]).unwrap();
            let encoded = trainer.model.encode(&prefix).unwrap();
            let goal: Vec<f32> = encoded
                .goal
                .expect("the encoding keeps the pointed position")
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            total += (0..3).map(|a| (goal[a] - last[a]).powi(2)).sum::<f32>().sqrt();
        }
        total / episode.keyframes() as f32
    };
    let (supervised, unsupervised) = (pointing(1.0), pointing(0.0));
    assert!(
        supervised < 0.5 * unsupervised,
        "pointed {supervised:.3} from the goal with its loss, {unsupervised:.3} without"
    );
}

#[test]
fn the_position_pointer_reads_the_instruction_caches_like_the_prefix_and_needs_the_endpoint() {
    use flowram::policy::inputs::{Augmentation, prefix_inputs, suffix_inputs};
    let mut config = tiny_config();
    config.model.position_pointer = true;
    config.model.instruction_adaln = false;
    config.flow.prediction = flowram::policy::flow::Prediction::Velocity;
    let err = config.validate().unwrap_err().to_string();
    assert!(err.contains("flow.prediction") && err.contains("position_pointer"), "{err}");
    config.flow.prediction = flowram::policy::flow::Prediction::Endpoint;
    config.validate().unwrap();
    let mut no_pointer = config.clone();
    no_pointer.model.position_pointer = false;
    no_pointer.flow.pointer_weight = 1.0;
    let err = no_pointer.validate().unwrap_err().to_string();
    assert!(err.contains("flow.pointer_weight"), "{err}");
    let observation = Observation::from_episode(demonstration(), 0).unwrap();
    let action = [[0.1f32, -0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]];
    let predict = |o: &Observation| -> (Vec<f32>, Vec<f32>) {
        let mut policy = Policy::random(&config, text()).unwrap();
        let prepared = policy.prepare(o).unwrap();
        let observations = [(&prepared, Augmentation::NONE)];
        let prefix = prefix_inputs(&config, &observations).unwrap();
        let suffix = suffix_inputs(&config, &observations, &[0], &action, &[0.3], &config.radius_schedule).unwrap();
        let out = policy.model.forward(&prefix, &suffix).unwrap();
        let (log_weights, candidates) = out.pointer.expect("the training forward returns the pointer's attention");
        let n = config.observation.semantic_tokens + config.observation.geometric_tokens;
        assert_eq!((log_weights.dims(), candidates.dims()), (&[1, n][..], &[1, n, 3][..]));
        let total: f32 = log_weights.exp().unwrap().sum_all().unwrap().to_scalar().unwrap();
        assert!((total - 1.0).abs() < 1e-4, "the attention sums to {total}");
        let whole = out.velocity.to_vec2::<f32>().unwrap();
        let encoded = policy.model.encode(&prefix).unwrap();
        assert!(encoded.pointer.is_some(), "the encoding keeps the pointer's memory");
        let cached = policy.model.step(&encoded.repeat(1).unwrap(), &suffix).unwrap();
        (whole[0].clone(), cached.velocity.to_vec2::<f32>().unwrap()[0].clone())
    };
    let (whole, cached) = predict(&observation);
    for (a, b) in whole.iter().zip(&cached) {
        assert!((a - b).abs() < 1e-4, "training forward {whole:?}, cached inference {cached:?}");
    }
    // The pointer's own path: with sentence pooling and no AdaLN, the sentence embedding reaches
    // nothing but the pointer's query. Changing it alone moves the position and leaves the
    // rotation (read from the action token alone) exactly as it was.
    let mut sentence = config.clone();
    sentence.model.instruction_pooling = InstructionPooling::Sentence;
    let mut policy = Policy::random(&sentence, text()).unwrap();
    let prepared = policy.prepare(&observation).unwrap();
    let observations = [(&prepared, Augmentation::NONE)];
    let prefix = prefix_inputs(&sentence, &observations).unwrap();
    let suffix = suffix_inputs(&sentence, &observations, &[0], &action, &[0.3], &sentence.radius_schedule).unwrap();
    let other = flowram::policy::network::model::PrefixInputs {
        instruction: prefix.instruction.neg().unwrap(),
        ..prefix.clone()
    };
    let told = policy.model.forward(&prefix, &suffix).unwrap().velocity.to_vec2::<f32>().unwrap();
    let swapped = policy.model.forward(&other, &suffix).unwrap().velocity.to_vec2::<f32>().unwrap();
    assert!(told[0][..3].iter().zip(&swapped[0][..3]).any(|(a, b)| (a - b).abs() > 1e-6), "{told:?} vs {swapped:?}");
    assert_eq!(told[0][3..], swapped[0][3..], "the rotation read the sentence embedding");
}

#[test]
fn point_colour_adds_a_function_of_each_feature_pixels_raw_colour() {
    use flowram::policy::inputs::{Augmentation, prefix_inputs};
    let plain = tiny_config();
    let mut coloured = plain.clone();
    coloured.model.point_colour = true;
    let observation = Observation::from_episode(demonstration(), 0).unwrap();
    // Same seed: the variables both models share (the image encoder) start from the same values,
    // so the difference of their features is the colour MLP alone.
    let features =
        |config: &PolicyConfig, images: Option<&candle_core::Tensor>| -> (Vec<Vec<f32>>, candle_core::Tensor) {
            let mut policy = Policy::random(config, text()).unwrap();
            let prepared = policy.prepare(&observation).unwrap();
            let mut prefix = prefix_inputs(config, &[(&prepared, Augmentation::NONE)]).unwrap();
            if let Some(images) = images {
                prefix.images = images.clone();
            }
            (policy.model.image_features(&prefix.images).unwrap().to_vec2().unwrap(), prefix.images)
        };
    let (base, images) = features(&plain, None);
    // Paint the first camera's top-left 4 x 4 cell and the one beside it the same flat colour, and
    // the cell below them another.
    let stride = plain.observation.feature_stride;
    let mut pixels = images.to_dtype(candle_core::DType::U8).unwrap().flatten_all().unwrap().to_vec1::<u8>().unwrap();
    let size = plain.observation.image_size;
    for (row0, col0, rgb) in [(0, 0, [200u8, 10, 10]), (0, stride, [200, 10, 10]), (stride, 0, [100, 5, 5])] {
        for ch in 0..3 {
            for r in row0..row0 + stride {
                for c in col0..col0 + stride {
                    pixels[(ch * size + r) * size + c] = rgb[ch];
                }
            }
        }
    }
    let painted = candle_core::Tensor::from_vec(pixels, images.shape(), images.device()).unwrap();
    let (base_painted, _) = features(&plain, Some(&painted));
    let (with_colour, _) = features(&coloured, Some(&painted));
    let cells_per_row = size / stride;
    let diff =
        |cell: usize| -> Vec<f32> { with_colour[cell].iter().zip(&base_painted[cell]).map(|(a, b)| a - b).collect() };
    let (a, b, c) = (diff(0), diff(1), diff(cells_per_row));
    assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-5), "equal colours, different colour features");
    assert!(a.iter().zip(&c).any(|(x, y)| (x - y).abs() > 1e-3), "red and its half-brightness pair look the same");
    assert!(a.iter().any(|x| x.abs() > 1e-3), "the colour feature is zero");
    assert_ne!(base[0], base_painted[0], "painting did not change the image");
}

#[test]
fn the_relational_pointer_needs_both_pointers_starts_as_one_pointer_and_learns_its_beta() {
    use flowram::policy::inputs::{Augmentation, prefix_inputs, suffix_inputs};
    let mut config = tiny_config();
    config.model.position_pointer = true;
    config.model.instruction_pointer = false;
    config.model.relational_pointer = true;
    let err = config.validate().unwrap_err().to_string();
    assert!(err.contains("model.relational_pointer") && err.contains("instruction_pointer"), "{err}");
    config.model.instruction_pointer = true;
    config.flow.goal_weight = 1.0;
    config.train.batch = 8;
    config.validate().unwrap();
    let mut single = config.clone();
    single.model.relational_pointer = false;
    // Same seed and variable names, so the same weights; beta starts at zero, so the same output,
    // through the training forward and through the cached inference path.
    let observation = Observation::from_episode(demonstration(), 0).unwrap();
    let action = [[0.1f32, -0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]];
    let outputs = |config: &PolicyConfig| -> (Vec<f32>, Vec<f32>) {
        let mut policy = Policy::random(config, text()).unwrap();
        let prepared = policy.prepare(&observation).unwrap();
        let observations = [(&prepared, Augmentation::NONE)];
        let prefix = prefix_inputs(config, &observations).unwrap();
        let suffix = suffix_inputs(config, &observations, &[0], &action, &[0.3], &config.radius_schedule).unwrap();
        let whole = policy.model.forward(&prefix, &suffix).unwrap().velocity.flatten_all().unwrap().to_vec1().unwrap();
        let encoded = policy.model.encode(&prefix).unwrap();
        let cached = policy.model.step(&encoded, &suffix).unwrap().velocity.flatten_all().unwrap().to_vec1().unwrap();
        (whole, cached)
    };
    let (relational, single) = (outputs(&config), outputs(&single));
    for (a, b) in relational.0.iter().zip(&single.0).chain(relational.1.iter().zip(&single.1)) {
        assert!((a - b).abs() < 1e-5, "relational {relational:?}, single pointer {single:?}");
    }
    // Training reaches beta (the flow loss's gradient through p - g).
    assert!(norm_after_training(&config, "relation.weight", 20) > 0.0, "beta's weights are still zero after 20 steps");
}

/// The squared norm of the variable `name` after `steps` training steps of `config` on the
/// demonstration (a zero-initialised branch that training reaches is no longer zero).
fn norm_after_training(config: &PolicyConfig, name: &str, steps: usize) -> f32 {
    let mut data = TrainingData::from_episodes(vec![demonstration().clone()]).unwrap();
    let mut text = text();
    let mut trainer = Trainer::new(config).unwrap();
    for _ in 0..steps {
        trainer.train_step(&mut data, &mut text).unwrap();
    }
    let vars = trainer.varmap.data().lock().unwrap();
    let weight = vars.get(name).unwrap_or_else(|| panic!("{name} is not a trained variable"));
    weight.as_tensor().sqr().unwrap().sum_all().unwrap().to_scalar().unwrap()
}

/// tiny_config with both pointers, the relation, and their losses.
fn relational_config() -> PolicyConfig {
    let mut config = tiny_config();
    config.model.position_pointer = true;
    config.model.instruction_pointer = true;
    config.model.relational_pointer = true;
    config.flow.goal_weight = 1.0;
    config.flow.pointer_weight = 1.0;
    config.train.batch = 8;
    config.validate().unwrap();
    config
}

#[test]
fn the_relational_pointer_target_needs_the_relation_and_moves_the_pointer_loss_once_beta_is_learnt() {
    let config = relational_config();
    let mut relational = config.clone();
    relational.flow.pointer_target = PointerTarget::Relational;
    relational.validate().unwrap();
    for broken in [
        PolicyConfig {
            flow: flowram::policy::config::FlowConfig { pointer_weight: 0.0, ..relational.flow.clone() },
            ..relational.clone()
        },
        PolicyConfig {
            model: flowram::policy::config::ModelConfig { relational_pointer: false, ..relational.model.clone() },
            ..relational.clone()
        },
    ] {
        let err = broken.validate().unwrap_err().to_string();
        assert!(err.contains("flow.pointer_target") && err.contains("relational_pointer"), "{err}");
    }
    // The same seed: the first step's target is the keyframe in both (beta starts at zero), so the
    // same loss; once beta has moved, the relational target moves the pointer's loss.
    let losses = |config: &PolicyConfig| -> Vec<StepLoss> {
        let mut data = TrainingData::from_episodes(vec![demonstration().clone()]).unwrap();
        let mut text = text();
        let mut trainer = Trainer::new(config).unwrap();
        (0..6).map(|_| trainer.train_step(&mut data, &mut text).unwrap()).collect()
    };
    let (keyframe, moved) = (losses(&config), losses(&relational));
    assert_eq!(keyframe[0], moved[0]);
    assert!(moved.iter().all(|l| l.total.is_finite()), "{moved:?}");
    assert!(keyframe.iter().zip(&moved).skip(1).any(|(a, b)| a.total != b.total), "{keyframe:?} against {moved:?}");
}

/// The loss of a fresh model's first training step on the demonstration (same seed and data for
/// every config: only what the config changes differs).
fn first_step(config: &PolicyConfig) -> StepLoss {
    let mut data = TrainingData::from_episodes(vec![demonstration().clone()]).unwrap();
    let mut text = text();
    Trainer::new(config).unwrap().train_step(&mut data, &mut text).unwrap()
}

#[test]
fn the_goal_under_the_keyframe_needs_the_goal_loss_and_changes_it_from_the_first_step() {
    use flowram::policy::config::GoalTarget;
    let config = relational_config();
    let mut under = config.clone();
    under.flow.goal_target = GoalTarget::Under;
    under.validate().unwrap();
    let mut no_goal = under.clone();
    no_goal.flow.goal_weight = 0.0;
    let err = no_goal.validate().unwrap_err().to_string();
    assert!(err.contains("flow.goal_target") && err.contains("goal_weight"), "{err}");
    // The same seed and weights: only the goal loss's target differs, from the first step on.
    let (keyframe, horizontal) = (first_step(&config), first_step(&under));
    assert!(horizontal.total.is_finite(), "{horizontal:?}");
    assert_eq!(keyframe.cfm, horizontal.cfm);
    assert_ne!(keyframe.total, horizontal.total);
}

#[test]
fn the_goal_at_the_stages_end_needs_the_goal_loss_and_moves_its_target_to_the_press() {
    use flowram::policy::config::{GoalKeyframe, GoalTarget};
    let config = relational_config();
    let mut stage = config.clone();
    stage.flow.goal_keyframe = GoalKeyframe::StageEnd;
    stage.validate().unwrap();
    let mut no_goal = stage.clone();
    no_goal.flow.goal_weight = 0.0;
    let err = no_goal.validate().unwrap_err().to_string();
    assert!(err.contains("flow.goal_keyframe") && err.contains("goal_weight"), "{err}");
    // Not serialised when "last": configs written before the option are unchanged.
    let json = serde_json::to_value(&config).unwrap();
    assert!(json["flow"].get("goal_keyframe").is_none(), "{}", json["flow"]);
    assert_eq!(serde_json::to_value(&stage).unwrap()["flow"]["goal_keyframe"], "stage_end");
    // The demonstration presses one button: above it, the press, up 8 cm. Its stage ends at the
    // press, 8 cm under the last keyframe: a different 3-D target from the first step on, and
    // the same horizontal one ("under").
    let (last, press) = (first_step(&config), first_step(&stage));
    assert!(press.total.is_finite(), "{press:?}");
    assert_eq!(last.cfm, press.cfm);
    assert_ne!(last.total, press.total);
    let mut under = config.clone();
    under.flow.goal_target = GoalTarget::Under;
    let mut under_stage = under.clone();
    under_stage.flow.goal_keyframe = GoalKeyframe::StageEnd;
    assert_eq!(first_step(&under).total, first_step(&under_stage).total);
}

#[test]
fn the_rotation_reading_the_relation_needs_it_starts_switched_off_and_learns() {
    let mut config = relational_config();
    config.model.relation_rotation = true;
    config.validate().unwrap();
    let mut no_relation = config.clone();
    no_relation.model.relational_pointer = false;
    let err = no_relation.validate().unwrap_err().to_string();
    assert!(err.contains("model.relation_rotation") && err.contains("relational_pointer"), "{err}");
    let mut without = config.clone();
    without.model.relation_rotation = false;
    // The output layer starts at zero: the same samples as without the branch (initial values
    // are keyed by the variable's name, so every other variable starts the same).
    let observation = Observation::from_episode(demonstration(), 0).unwrap();
    let options = SamplingOptions::new(2, 2, 5);
    let samples =
        |config: &PolicyConfig| Policy::random(config, text()).unwrap().predict(&observation, &options).unwrap();
    assert_eq!(samples(&config), samples(&without));
    // The branch that also reads the action token: only with the branch, and also switched off.
    let mut token = config.clone();
    token.model.relation_rotation_reads_token = true;
    token.validate().unwrap();
    assert_eq!(samples(&token), samples(&without));
    let mut orphan = without.clone();
    orphan.model.relation_rotation_reads_token = true;
    let err = orphan.validate().unwrap_err().to_string();
    assert!(err.contains("model.relation_rotation_reads_token") && err.contains("relation_rotation"), "{err}");
    let norm = norm_after_training(&config, "relation_rotation.1.weight", 20);
    assert!(norm > 0.0, "the branch's output layer is still zero after 20 steps");
}

#[test]
fn predict_explained_reads_out_each_samples_pointers_without_changing_the_samples() {
    let config = relational_config();
    let observation = Observation::from_episode(demonstration(), 0).unwrap();
    let options = SamplingOptions::new(2, 3, 7);
    let mut policy = Policy::random(&config, text()).unwrap();
    let explained = policy.predict_explained(&observation, &options).unwrap();
    assert_eq!(explained.poses, policy.predict(&observation, &options).unwrap());
    assert_eq!(explained.pointers.len(), 3);
    let (lo, hi) = (config.observation.workspace.min(), config.observation.workspace.max());
    for r in &explained.pointers {
        // p and g are attention-weighted means of token positions: inside the box.
        for x in [r.pointed, r.goal.expect("the relational pointer reads out g")] {
            assert!((0..3).all(|i| x[i] >= lo[i] - 1e-4 && x[i] <= hi[i] + 1e-4), "{x:?} outside {lo:?}..{hi:?}");
        }
        assert!(r.beta.is_some_and(f32::is_finite), "{r:?}");
    }
    // g reads the observation only (the instruction pointer is in the prefix): one g for all samples.
    let goals: Vec<_> = explained.pointers.iter().map(|r| r.goal).collect();
    assert!(goals.windows(2).all(|w| w[0] == w[1]), "{goals:?}");
    // Without the position pointer there is nothing to read out.
    let mut plain = tiny_config();
    plain.model.position_pointer = false;
    plain.flow.pointer_weight = 0.0;
    plain.validate().unwrap();
    let mut policy = Policy::random(&plain, text()).unwrap();
    assert!(policy.predict_explained(&observation, &options).unwrap().pointers.is_empty());
}

#[test]
fn configs_written_before_the_conditioning_options_load_with_the_papers_choices() {
    // A checkpoint's config.json from before model.instruction_adaln, flow.prediction and
    // flow.time_sampling existed: it must load, and mean what it meant then.
    let mut json = serde_json::to_value(tiny_config()).unwrap();
    json["model"].as_object_mut().unwrap().remove("instruction_adaln");
    json["flow"].as_object_mut().unwrap().remove("prediction");
    json["flow"].as_object_mut().unwrap().remove("time_sampling");
    for (section, key) in [
        ("model", "instruction_pointer"),
        ("model", "position_pointer"),
        ("model", "point_colour"),
        ("model", "relational_pointer"),
        ("model", "relation_rotation"),
        ("model", "relation_rotation_reads_token"),
        ("flow", "pointer_weight"),
        ("flow", "pointer_sigma"),
        ("flow", "consensus"),
        ("flow", "pointer_sharpening"),
        ("flow", "pointer_target"),
        ("flow", "goal_target"),
        ("flow", "goal_keyframe"),
        ("observation", "proprio_history"),
    ] {
        json[section].as_object_mut().unwrap().remove(key);
    }
    let config: PolicyConfig = serde_json::from_value(json).unwrap();
    assert!(!config.model.instruction_adaln);
    assert_eq!(config.flow.prediction, flowram::policy::flow::Prediction::Velocity);
    assert_eq!(config.flow.time_sampling, flowram::policy::flow::FlowTimeSampling::Uniform);
    assert!(!config.model.instruction_pointer && !config.model.position_pointer && !config.model.point_colour);
    assert!(!config.model.relational_pointer && !config.model.relation_rotation);
    assert!(!config.model.relation_rotation_reads_token);
    assert_eq!((config.flow.pointer_weight, config.flow.pointer_sigma), (0.0, 0.02));
    assert_eq!(config.observation.proprio_history, 1);
    assert_eq!(config.flow.consensus, Consensus::Medoid);
    assert_eq!(config.flow.pointer_sharpening, PointerSharpening::OFF);
    assert_eq!(config.flow.pointer_target, PointerTarget::Keyframe);
    assert_eq!(config.flow.goal_target, flowram::policy::config::GoalTarget::Keyframe);
    assert_eq!(config.flow.goal_keyframe, flowram::policy::config::GoalKeyframe::Last);
    // a command line's --pointer-temperature replaces the temperature only, and only when given
    let set = PointerSharpening { temperature: 0.5, until: 0.3, ..PointerSharpening::OFF };
    assert_eq!(set.with_temperature(None), set);
    assert_eq!(
        set.with_temperature(Some(0.1)),
        PointerSharpening { temperature: 0.1, until: 0.3, ..PointerSharpening::OFF }
    );
    config.validate().unwrap();
    // The consensus rule is one of two names; another is refused with the field and the choices.
    let mut json = serde_json::to_value(tiny_config()).unwrap();
    json["flow"]["consensus"] = "mode".into();
    assert_eq!(serde_json::from_value::<PolicyConfig>(json.clone()).unwrap().flow.consensus, Consensus::Mode);
    json["flow"]["consensus"] = "mean".into();
    let message = serde_json::from_value::<PolicyConfig>(json).unwrap_err().to_string();
    assert!(message.contains("mean") && message.contains("medoid") && message.contains("mode"), "{message}");
}

#[test]
fn several_flow_samples_of_one_observation_share_its_encoding() {
    use flowram::policy::inputs::{Augmentation, prefix_inputs, suffix_inputs};
    // train.flow_samples: the training forward takes K flow samples per observation (sample i
    // belongs to observation i / K); each must come out as if run alone with its observation.
    let config = tiny_config();
    let mut policy = Policy::random(&config, text()).unwrap();
    let episode = demonstration();
    let prepared: Vec<_> =
        (0..2).map(|k| policy.prepare(&Observation::from_episode(episode, k).unwrap()).unwrap()).collect();
    let actions: Vec<[f32; 9]> =
        (0..4).map(|i| std::array::from_fn(|d| 0.1 * (i as f32 + 1.0) * if d % 2 == 0 { 1.0 } else { -0.5 })).collect();
    let t = [0.1f32, 0.7, 0.3, 0.95];
    let owner = [0usize, 0, 1, 1];
    let schedule = &config.radius_schedule;
    let observations: Vec<_> = prepared.iter().map(|p| (p, Augmentation::NONE)).collect();
    let per_sample: Vec<_> = owner.iter().map(|&o| observations[o]).collect();
    let prefix = prefix_inputs(&config, &observations).unwrap();
    let suffix = suffix_inputs(&config, &per_sample, &owner, &actions, &t, schedule).unwrap();
    let together = policy.model.forward(&prefix, &suffix).unwrap().velocity.to_vec2::<f32>().unwrap();
    for i in 0..4 {
        let alone_prefix = prefix_inputs(&config, &[observations[owner[i]]]).unwrap();
        let alone_suffix =
            suffix_inputs(&config, &[observations[owner[i]]], &[0], &[actions[i]], &[t[i]], schedule).unwrap();
        let alone = policy.model.forward(&alone_prefix, &alone_suffix).unwrap().velocity.to_vec2::<f32>().unwrap();
        for (a, b) in together[i].iter().zip(&alone[0]) {
            assert!((a - b).abs() < 1e-4, "sample {i}: {:?} together, {:?} alone", together[i], alone[0]);
        }
    }
    // Samples that cannot be split evenly over the observations are refused.
    let odd = suffix_inputs(&config, &per_sample[..3], &owner[..3], &actions[..3], &t[..3], schedule).unwrap();
    assert!(policy.model.forward(&prefix, &odd).is_err());
}

#[test]
fn a_policy_sees_only_the_cameras_its_config_names() {
    let episode = demonstration(); // front and left_shoulder
    let observation = Observation::from_episode(episode, 0).unwrap();
    let mut config = tiny_config();
    config.observation.cameras = vec!["left_shoulder".into()];
    let mut policy = Policy::random(&config, text()).unwrap();
    let prepared = policy.prepare(&observation).unwrap();
    assert_eq!(prepared.cameras, 1);
    let side = 3 * 64 * 64;
    let rgb = &observation.cameras[1].rgb;
    assert_eq!(prepared.images[..side / 3], rgb.iter().step_by(3).copied().collect::<Vec<u8>>()[..]);
    policy.predict(&observation, &SamplingOptions::new(2, 1, 0)).unwrap();
    // A camera the observation does not have is named, with what to do.
    config.observation.cameras = vec!["overhead".into()];
    let mut policy = Policy::random(&config, text()).unwrap();
    let message = policy.prepare(&observation).unwrap_err().to_string();
    assert!(message.contains("overhead") && message.contains("--cameras"), "{message}");
    // Names must be distinct.
    config.observation.cameras = vec!["front".into(), "front".into()];
    assert!(config.validate().is_err());
}

#[test]
fn shipped_policy_configs_load_and_the_ten_task_box_holds_every_expert_keyframe() {
    let dir = flowram::deps::models_dir().join("policy");
    let mut loaded = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            PolicyConfig::from_toml_file(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            loaded += 1;
        }
    }
    assert!(loaded >= 3, "paper.toml, cpu.toml, ten-tasks.toml");
    // the ten-task recipe is the five-task one with a wider box, from before the position pointer
    // (arm P5 of docs/experiments.md came after the ten-task checkpoint shipped)
    let ten = PolicyConfig::from_toml_file(&dir.join("ten-tasks.toml")).unwrap();
    let mut same = ten.clone();
    let cpu = PolicyConfig::cpu_default().unwrap();
    same.observation.workspace = cpu.observation.workspace;
    same.model.position_pointer = true;
    same.flow.pointer_weight = cpu.flow.pointer_weight;
    // and from before the consensus of samples (docs/experiments.md, C8 and RN5)
    same.flow.consensus_samples = cpu.flow.consensus_samples;
    assert_eq!(same, cpu);
    let ws = &ten.observation.workspace;
    for task in flowram::tasks::all() {
        let mut world = flowram::tasks::load_world(task.as_ref()).unwrap();
        for seed in 0..task.variation_count().min(3) as u64 {
            let variation = seed as usize % task.variation_count();
            let (keyframes, _) =
                flowram::rollout::episode::expert_plan(task.as_ref(), &mut world, variation, seed).unwrap();
            for k in &keyframes {
                let p = k.position.map(|v| v as f32);
                assert!(ws.contains(p), "{} seed {seed}: keyframe {p:?} outside the ten-task box", task.name());
            }
        }
    }
}

/// The AdaLN condition the Mamba blocks are modulated by, for observation 1 of the
/// demonstration taken after `keyframe` keyframes, from a fresh seeded model whose variables
/// `set` has changed (their modulation starts at zero, adaLN-Zero, so a fresh model's output
/// cannot show the condition).
fn condition_at(
    config: &PolicyConfig,
    text: &mut TextEncoder,
    keyframe: usize,
    set: impl FnOnce(&std::collections::HashMap<String, candle_core::Var>),
) -> Vec<f32> {
    let observation = Observation { keyframe, ..Observation::from_episode(demonstration(), 1).unwrap() };
    condition_of(config, text, &observation, set)
}

/// The AdaLN condition of `observation` (as [`condition_at`]).
fn condition_of(
    config: &PolicyConfig,
    text: &mut TextEncoder,
    observation: &Observation,
    set: impl FnOnce(&std::collections::HashMap<String, candle_core::Var>),
) -> Vec<f32> {
    use flowram::policy::inputs::{Augmentation, prefix_inputs};
    let varmap = candle_nn::VarMap::new();
    let vb = flowram::policy::network::init::seeded_var_builder(&varmap, 0, &candle_core::Device::Cpu);
    let model = flowram::policy::network::model::FlowRam::new(config, vb).unwrap();
    set(&varmap.data().lock().unwrap());
    let observation = observation.clone();
    let prepared = flowram::policy::inputs::prepare(&observation, config, text).unwrap();
    let prefix = prefix_inputs(config, &[(&prepared, Augmentation::NONE)]).unwrap();
    model.encode(&prefix).unwrap().condition.to_vec2::<f32>().unwrap()[0].clone()
}

#[test]
fn the_keyframe_index_reaches_the_condition_only_when_configured() {
    use candle_core::{DType, Device, Tensor};
    let episode = demonstration();
    // a plain expert episode: observation k comes after k keyframes
    for k in 0..episode.keyframes() {
        assert_eq!(Observation::from_episode(episode, k).unwrap().keyframe, k);
    }
    let mut config = tiny_config();
    config.observation.keyframe_index = true;
    let mut text = text();
    let condition = |config: &PolicyConfig, text: &mut TextEncoder, keyframe: usize, table: Option<&Tensor>| {
        condition_at(config, text, keyframe, |vars| {
            assert_eq!(vars.contains_key("keyframe_embedding"), config.observation.keyframe_index);
            if let (Some(var), Some(table)) = (vars.get("keyframe_embedding"), table) {
                var.set(table).unwrap();
            }
        })
    };
    // zero-initialised: a new model starts as the one without the index
    assert_eq!(condition(&config, &mut text, 0, None), condition(&config, &mut text, 4, None));
    let rows = flowram::policy::config::MAX_KEYFRAME_INDEX + 1;
    let c = config.model.channels;
    let table = Tensor::randn(0.0f32, 1.0, (rows, c), &Device::Cpu).unwrap().to_dtype(DType::F32).unwrap();
    let (first, fifth) =
        (condition(&config, &mut text, 0, Some(&table)), condition(&config, &mut text, 4, Some(&table)));
    // the condition moves by exactly the difference of the table's rows 4 and 0
    let rows_of = table.to_vec2::<f32>().unwrap();
    for i in 0..c {
        let (moved, expected) = (fifth[i] - first[i], rows_of[4][i] - rows_of[0][i]);
        assert!((moved - expected).abs() < 1e-4, "channel {i}: moved {moved}, the table says {expected}");
    }
    // past the table's end: the last row, as the last index
    let (last, beyond) =
        (condition(&config, &mut text, rows - 1, Some(&table)), condition(&config, &mut text, 400, Some(&table)));
    assert_eq!(last, beyond);
    // off (the paper): no table, and the index changes nothing
    config.observation.keyframe_index = false;
    assert_eq!(condition(&config, &mut text, 0, None), condition(&config, &mut text, 4, None));
}

#[test]
fn the_gripper_history_reaches_the_condition_only_when_configured() {
    let episode = demonstration();
    // a plain expert episode: observation k remembers the k poses before it, most recent first
    for k in 0..episode.keyframes() {
        let observation = Observation::from_episode(episode, k).unwrap();
        let expected: Vec<[f32; 8]> =
            (0..k).rev().map(|i| std::array::from_fn(|j| episode.proprio[i * 8 + j])).collect();
        assert_eq!(observation.history, expected, "keyframe {k}");
    }
    let mut config = tiny_config();
    config.observation.proprio_history = 3;
    let mut text = text();
    let mut condition = |config: &PolicyConfig, observation: &Observation| {
        condition_of(config, &mut text, observation, |vars| {
            let inputs = vars["proprio_mlp.0.weight"].as_tensor().dims().to_vec();
            assert_eq!(inputs[1], 10 * config.observation.proprio_history, "{inputs:?}");
        })
    };
    let observation = Observation::from_episode(episode, 2).unwrap();
    assert_eq!(observation.history.len(), 2);
    let mut elsewhere = observation.clone();
    elsewhere.history[1][0] += 0.05;
    let mut closed = observation.clone();
    closed.history[0][7] = 1.0 - closed.history[0][7];
    let mut shorter = observation.clone();
    shorter.history.truncate(1);
    let mut padded = shorter.clone();
    padded.history.push(padded.history[0]);
    let base = condition(&config, &observation);
    // where the gripper was two keyframes ago, and whether it was open one keyframe ago, move it
    assert_ne!(base, condition(&config, &elsewhere));
    assert_ne!(base, condition(&config, &closed));
    // a short history repeats its oldest pose
    assert_eq!(condition(&config, &shorter), condition(&config, &padded));
    // a history longer than configured is not read
    let mut longer = observation.clone();
    longer.history.push([9.0; 8]);
    assert_eq!(base, condition(&config, &longer));
    // 1 (the default, the checkpoints before it): the history changes nothing
    config.observation.proprio_history = 1;
    assert_eq!(condition(&config, &observation), condition(&config, &elsewhere));
    for bad in [0, flowram::policy::config::MAX_PROPRIO_HISTORY + 1] {
        config.observation.proprio_history = bad;
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("observation.proprio_history"), "{err}");
    }
}

#[test]
fn conditioned_pooling_lets_the_keyframe_index_choose_the_instruction_words() {
    use candle_core::{Device, Tensor};
    let mut config = tiny_config();
    config.observation.keyframe_index = true;
    config.model.instruction_adaln = true;
    let mut text = text();
    let c = config.model.channels;
    let rows = flowram::policy::config::MAX_KEYFRAME_INDEX + 1;
    // Seeded: candle's `randn` draws from an unseeded generator, and an unlucky draw once left
    // the pooling's change under the threshold below (0.0008, session 29).
    let mut rng = <rand::rngs::StdRng as rand::SeedableRng>::seed_from_u64(7);
    let mut normal = |shape: (usize, usize)| {
        let values = (0..shape.0 * shape.1).map(|_| flowram::policy::flow::standard_normal(&mut rng) as f32).collect();
        Tensor::from_vec(values, shape, &Device::Cpu).unwrap()
    };
    let (table, query) = (normal((rows, c)), normal((c, c)));
    // The AdaLN condition at keyframe index k, with the index table above and, when `trained`,
    // the pooling's query weights above (a fresh model's query is zero).
    let condition = |config: &PolicyConfig, text: &mut TextEncoder, keyframe: usize, trained: bool, words: bool| {
        condition_at(config, text, keyframe, |vars| {
            let conditioned = config.model.instruction_pooling == InstructionPooling::Conditioned;
            assert_eq!(vars.contains_key("pooling_query.query.weight"), conditioned);
            vars["keyframe_embedding"].set(&table).unwrap();
            if trained && conditioned {
                vars["pooling_query.query.weight"].set(&query).unwrap();
            }
            if !words && conditioned {
                // keys from the tokens' places in the instruction alone
                let key = &vars["pooling_query.key.weight"];
                key.set(&key.as_tensor().zeros_like().unwrap()).unwrap();
            }
        })
    };
    // How far the condition moves from index 0 to index 4 beyond the index table's own rows:
    // what the pooled instruction's change adds.
    let rows_of = table.to_vec2::<f32>().unwrap();
    let mut beyond_table = |config: &PolicyConfig, trained: bool, words: bool| -> f32 {
        let first = condition(config, &mut text, 0, trained, words);
        let fifth = condition(config, &mut text, 4, trained, words);
        (0..c).map(|i| ((fifth[i] - first[i]) - (rows_of[4][i] - rows_of[0][i])).abs()).fold(0.0, f32::max)
    };
    // "attention": the pooled instruction is the same at every index
    config.model.instruction_pooling = InstructionPooling::Attention;
    let attention = beyond_table(&config, true, true);
    assert!(attention < 1e-4, "attention pooling moved with the keyframe index by {attention}");
    // "conditioned", fresh: the query starts at zero, so it pools as "attention" does
    config.model.instruction_pooling = InstructionPooling::Conditioned;
    let fresh = beyond_table(&config, false, true);
    assert!(fresh < 1e-4, "a fresh conditioned pooling moved with the keyframe index by {fresh}");
    // "conditioned" with a query: the index chooses other words, and the condition shows it
    let trained = beyond_table(&config, true, true);
    assert!(trained > 1e-2, "the conditioned pooling did not follow the keyframe index ({trained})");
    // ... also through the embedding of each token's place alone ("the first colour word")
    let places = beyond_table(&config, true, false);
    assert!(places > 1e-2, "the tokens' places in the instruction did not reach the pooling ({places})");
}

#[test]
fn the_language_attention_starts_switched_off_reads_the_words_and_caches_like_the_prefix() {
    use candle_core::{Device, Tensor};
    use flowram::policy::inputs::{Augmentation, prefix_inputs, suffix_inputs};
    let mut config = tiny_config();
    config.model.language_attention_heads = 7;
    let err = config.validate().unwrap_err().to_string();
    assert!(err.contains("model.language_attention_heads") && err.contains("120"), "{err}");
    config.model.language_attention_heads = 4;
    config.validate().unwrap();
    // off (the default) is not written, so configs without it read and digest as before
    let json = serde_json::to_string(&tiny_config().model).unwrap();
    assert!(!json.contains("language_attention"), "{json}");
    let json = serde_json::to_string(&config.model).unwrap();
    assert_eq!(serde_json::from_str::<flowram::policy::config::ModelConfig>(&json).unwrap(), config.model);

    let mut text = text();
    let observation = Observation::from_episode(demonstration(), 1).unwrap();
    let prepared = flowram::policy::inputs::prepare(&observation, &config, &mut text).unwrap();
    let observations = [(&prepared, Augmentation::NONE)];
    let prefix = prefix_inputs(&config, &observations).unwrap();
    let action = [[0.1f32, -0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]];
    let suffix = suffix_inputs(&config, &observations, &[0], &action, &[0.6], &config.radius_schedule).unwrap();
    // another instruction's tokens: the first tokens' features reversed in order
    let lt = config.observation.language_tokens;
    let reversed: Vec<u32> = (0..lt as u32).rev().collect();
    let other = flowram::policy::network::model::PrefixInputs {
        language: prefix.language.index_select(&Tensor::new(reversed, &Device::Cpu).unwrap(), 1).unwrap(),
        ..prefix.clone()
    };
    let mut rng = <rand::rngs::StdRng as rand::SeedableRng>::seed_from_u64(3);
    let c = config.model.channels;
    let out: Vec<f32> = (0..c * c).map(|_| 0.2 * flowram::policy::flow::standard_normal(&mut rng) as f32).collect();
    let out = Tensor::from_vec(out, (c, c), &Device::Cpu).unwrap();
    // The velocity of one flow step from the training forward and from the cached inference,
    // the same seeded weights every time (`trained`: the output projection set).
    let velocity = |config: &PolicyConfig, prefix: &flowram::policy::network::model::PrefixInputs, trained: bool| {
        let varmap = candle_nn::VarMap::new();
        let vb = flowram::policy::network::init::seeded_var_builder(&varmap, 0, &Device::Cpu);
        let model = flowram::policy::network::model::FlowRam::new(config, vb).unwrap();
        let vars = varmap.data().lock().unwrap();
        assert_eq!(vars.contains_key("language_attention.out.weight"), config.model.language_attention_heads > 0);
        if trained {
            vars["language_attention.out.weight"].set(&out).unwrap();
        }
        drop(vars);
        let whole = model.forward(prefix, &suffix).unwrap().velocity.to_vec2::<f32>().unwrap()[0].clone();
        let encoded = model.encode(prefix).unwrap().repeat(3).unwrap();
        let suffix3 = suffix_inputs(
            config,
            &[(&prepared, Augmentation::NONE); 3],
            &[0, 0, 0],
            &[action[0]; 3],
            &[0.6; 3],
            &config.radius_schedule,
        )
        .unwrap();
        let cached = model.step(&encoded, &suffix3).unwrap().velocity.to_vec2::<f32>().unwrap()[2].clone();
        for (a, b) in whole.iter().zip(&cached) {
            assert!((a - b).abs() < 1e-4, "training forward {whole:?}, cached inference {cached:?}");
        }
        whole
    };
    let mut off = config.clone();
    off.model.language_attention_heads = 0;
    // fresh: the output projection is zero, so the model is exactly the one without it
    let without = velocity(&off, &prefix, false);
    assert_eq!(velocity(&config, &prefix, false), without);
    // with an output projection the prediction moves, and by how much depends on the words
    let read = velocity(&config, &prefix, true);
    let moved: Vec<f32> = read.iter().zip(&without).map(|(a, b)| a - b).collect();
    assert!(moved.iter().any(|m| m.abs() > 1e-3), "the attention did not move the prediction: {moved:?}");
    let without_other = velocity(&off, &other, false);
    let moved_other: Vec<f32> =
        velocity(&config, &other, true).iter().zip(&without_other).map(|(a, b)| a - b).collect();
    assert!(
        moved.iter().zip(&moved_other).any(|(a, b)| (a - b).abs() > 1e-4),
        "what the attention adds did not depend on the instruction's tokens: {moved:?} vs {moved_other:?}"
    );

    // `language_attention_reads = "pointer"`: only the position pointer's query reads it
    let mut pointer = config.clone();
    pointer.model.language_attention_reads = LanguageReads::Pointer;
    assert!(pointer.model.position_pointer, "the CPU default has the position pointer");
    pointer.validate().unwrap();
    let mut no_pointer = pointer.clone();
    no_pointer.model.position_pointer = false;
    let err = no_pointer.validate().unwrap_err().to_string();
    assert!(err.contains("model.language_attention_reads") && err.contains("position_pointer"), "{err}");
    let mut no_heads = pointer.clone();
    no_heads.model.language_attention_heads = 0;
    let err = no_heads.validate().unwrap_err().to_string();
    assert!(err.contains("model.language_attention_reads") && err.contains("language_attention_heads"), "{err}");
    let json = serde_json::to_string(&pointer.model).unwrap();
    assert!(json.contains(r#""language_attention_reads":"pointer""#), "{json}");
    assert_eq!(serde_json::from_str::<flowram::policy::config::ModelConfig>(&json).unwrap(), pointer.model);
    let mut token = pointer.clone();
    token.model.language_attention_reads = LanguageReads::Token;
    assert!(!serde_json::to_string(&token.model).unwrap().contains("language_attention_reads"));
    no_heads.model.language_attention_reads = LanguageReads::Token;
    let without = velocity(&no_heads, &prefix, false);
    let pointed = velocity(&pointer, &prefix, true);
    let everywhere = velocity(&token, &prefix, true);
    // the rotation (velocity[3..9]) is the plain token's; the position follows the pointer's read
    assert_eq!(pointed[3..], without[3..], "the rotation read the attention");
    assert!(everywhere[3..].iter().zip(&without[3..]).any(|(a, b)| (a - b).abs() > 1e-4), "{everywhere:?}");
    assert!(
        pointed[..3].iter().zip(&without[..3]).any(|(a, b)| (a - b).abs() > 1e-5),
        "the pointer's query did not read the attention: {pointed:?} vs {without:?}"
    );
}

/// A fresh model with the position pointer (its attention spread over the scene, so the
/// pointer's sampling options move its samples), its config, and an observation of the
/// demonstration.
fn fresh_pointer_policy() -> (PolicyConfig, Policy, Observation) {
    let config = tiny_config();
    assert!(config.model.position_pointer);
    let policy = Policy::random(&config, text()).unwrap();
    (config, policy, Observation::from_episode(demonstration(), 1).unwrap())
}

#[test]
fn the_pointers_posterior_is_as_trained_at_flow_time_0_and_moves_the_later_steps() {
    let (config, mut policy, observation) = fresh_pointer_policy();
    let mut explain = |steps: usize, posterior: bool| {
        let sharpening = PointerSharpening { posterior, ..PointerSharpening::OFF };
        let options = SamplingOptions { sharpening, ..SamplingOptions::new(steps, 2, 3) };
        policy.predict_explained(&observation, &options).unwrap()
    };
    // One Euler step runs at t = 0 only, where a_0 is pure noise and every candidate is as
    // likely as any other (the likelihood's centres t (x_i + c) are all 0): as trained, exactly.
    assert_eq!(explain(1, true), explain(1, false));
    // Later steps weigh the candidates by where the sample is.
    let (trained, posterior) = (explain(4, false), explain(4, true));
    assert_ne!(posterior.poses, trained.poses);
    assert_ne!(posterior.pointers, trained.pointers);
    // The option is written to a config only when on, so configs without it read as before.
    let json = serde_json::to_string(&config.flow.pointer_sharpening).unwrap();
    assert!(!json.contains("posterior"), "{json}");
    let on = PointerSharpening { posterior: true, ..PointerSharpening::OFF };
    let json = serde_json::to_string(&on).unwrap();
    assert_eq!(serde_json::from_str::<PointerSharpening>(&json).unwrap(), on);
    assert_eq!(PointerSharpening::OFF.with_posterior(true), on);
    assert_eq!(on.with_posterior(false), on, "a command line turns it on, never off");
}

#[test]
fn the_posteriors_candidate_width_spans_points_to_as_trained_and_is_validated() {
    let (config, mut policy, observation) = fresh_pointer_policy();
    let mut explain = |sharpening: PointerSharpening| {
        let options = SamplingOptions { sharpening, ..SamplingOptions::new(4, 2, 3) };
        policy.predict_explained(&observation, &options).unwrap()
    };
    let trained = explain(PointerSharpening::OFF);
    let points = PointerSharpening { posterior: true, ..PointerSharpening::OFF };
    let posterior = explain(points);
    // A width spreads each candidate, so the likelihood weighs them less than as points ...
    let wide = explain(PointerSharpening { posterior_width: 0.05, ..points });
    assert_ne!(wide.poses, posterior.poses);
    assert_ne!(wide.poses, trained.poses);
    // ... and a width far beyond the scene makes every candidate as likely: as trained.
    let boundless = explain(PointerSharpening { posterior_width: 1e9, ..points });
    assert_eq!(boundless.poses, trained.poses);
    // The command line's width turns the posterior on; none keeps the checkpoint's.
    assert_eq!(
        PointerSharpening::OFF.with_posterior_width(Some(0.02)),
        PointerSharpening { posterior_width: 0.02, ..points }
    );
    assert_eq!(points.with_posterior_width(None), points);
    // Written only when set, read back as written.
    let set = PointerSharpening { posterior_width: 0.02, ..points };
    let json = serde_json::to_string(&set).unwrap();
    assert_eq!(serde_json::from_str::<PointerSharpening>(&json).unwrap(), set);
    assert!(!serde_json::to_string(&points).unwrap().contains("width"));
    // Refused: a negative or non-finite width, and a width without the posterior.
    let mut bad = config.clone();
    for sharpening in [
        PointerSharpening { posterior_width: -0.01, ..points },
        PointerSharpening { posterior_width: f64::NAN, ..points },
        PointerSharpening { posterior_width: 0.02, ..PointerSharpening::OFF },
    ] {
        bad.flow.pointer_sharpening = sharpening;
        let message = bad.validate().unwrap_err().to_string();
        assert!(message.contains("flow.pointer_sharpening.posterior_width"), "{message}");
        let options = SamplingOptions { sharpening, ..SamplingOptions::new(4, 2, 3) };
        let message = policy.predict(&observation, &options).unwrap_err().to_string();
        assert!(message.contains("posterior_width"), "{message}");
    }
}

#[test]
fn the_pointer_sharpening_changes_only_the_steps_before_its_flow_time() {
    // A fresh model with the position pointer: its attention is spread over the scene, so
    // dividing the scores by a small temperature moves the pointed position.
    let (config, mut policy, observation) = fresh_pointer_policy();
    let mut predict = |sharpening: PointerSharpening| {
        let options = SamplingOptions { sharpening, ..SamplingOptions::new(4, 2, 3) };
        policy.predict(&observation, &options).unwrap()
    };
    let trained = predict(PointerSharpening::OFF);
    // No step before flow time 0; a temperature of 1 divides nothing.
    assert_eq!(predict(PointerSharpening { temperature: 0.05, until: 0.0, ..PointerSharpening::OFF }), trained);
    assert_eq!(predict(PointerSharpening { temperature: 1.0, until: 1.0, ..PointerSharpening::OFF }), trained);
    let half = predict(PointerSharpening { temperature: 0.05, until: 0.5, ..PointerSharpening::OFF });
    assert_ne!(half, trained);
    // 4 steps at t = 0, 0.25, 0.5, 0.75: until 0.3 sharpens the same two steps as 0.5, 0.51 and
    // 1.0 sharpen more (t < until, strictly).
    assert_eq!(predict(PointerSharpening { temperature: 0.05, until: 0.3, ..PointerSharpening::OFF }), half);
    assert_ne!(predict(PointerSharpening { temperature: 0.05, until: 0.51, ..PointerSharpening::OFF }), half);
    assert_ne!(predict(PointerSharpening { temperature: 0.05, until: 1.0, ..PointerSharpening::OFF }), half);
    // The config refuses a temperature that is not positive and a flow time outside [0, 1].
    let mut bad = config.clone();
    bad.flow.pointer_sharpening.temperature = 0.0;
    let message = bad.validate().unwrap_err().to_string();
    assert!(message.contains("flow.pointer_sharpening.temperature"), "{message}");
    bad.flow.pointer_sharpening = PointerSharpening { temperature: 0.1, until: 1.5, ..PointerSharpening::OFF };
    assert!(bad.validate().unwrap_err().to_string().contains("flow.pointer_sharpening.until"));
}

#[test]
fn the_instructions_guidance_is_as_trained_at_1_the_null_pointer_at_0_and_is_validated() {
    let (config, mut policy, observation) = fresh_pointer_policy();
    let mut explain = |observation: &Observation, steps: usize, guidance: f64| {
        let sharpening = PointerSharpening { guidance, ..PointerSharpening::OFF };
        let options = SamplingOptions { sharpening, ..SamplingOptions::new(steps, 2, 3) };
        policy.predict_explained(observation, &options).unwrap()
    };
    let trained = explain(&observation, 4, 1.0);
    // Above 1 the pointer's scores move away from the null instruction's, so the samples move.
    let guided = explain(&observation, 4, 3.0);
    assert_ne!(guided.poses, trained.poses);
    assert_ne!(guided.pointers, trained.pointers);
    // At 0 the pointer is the null instruction's: at the first Euler step (t = 0, the same
    // noise and geometric tokens) it points exactly where the empty instruction's does.
    let mut empty = observation.clone();
    empty.instruction = flowram::policy::inputs::NULL_INSTRUCTION.to_string();
    assert_ne!(empty.instruction, observation.instruction);
    let null = explain(&empty, 1, 1.0);
    let unconditional = explain(&observation, 1, 0.0);
    let pointed = |s: &flowram::policy::inference::Samples| s.pointers.iter().map(|p| p.pointed).collect::<Vec<_>>();
    assert_eq!(pointed(&unconditional), pointed(&null));
    assert_ne!(pointed(&explain(&observation, 1, 1.0)), pointed(&null), "the instruction does not move the pointer");
    // Written only when not 1, read back as written; a command line's value replaces it.
    assert!(!serde_json::to_string(&config.flow.pointer_sharpening).unwrap().contains("guidance"));
    let set = PointerSharpening { guidance: 2.0, ..PointerSharpening::OFF };
    let json = serde_json::to_string(&set).unwrap();
    assert_eq!(serde_json::from_str::<PointerSharpening>(&json).unwrap(), set);
    assert_eq!(PointerSharpening::OFF.with_guidance(Some(2.0)), set);
    assert_eq!(set.with_guidance(None), set);
    // The direction: s_null + w (s - s_null), so at w = 2 the log-odds between two candidates
    // are twice the instructed ones less the null's.
    let device = candle_core::Device::Cpu;
    let s = candle_core::Tensor::new(&[[[1.0f32, 3.0, -2.0]]], &device).unwrap();
    let null = candle_core::Tensor::new(&[[[0.5f32, 0.5, 1.0]]], &device).unwrap();
    let guided = flowram::policy::network::model::guided_scores(&s, &null, 2.0).unwrap();
    assert_eq!(guided.flatten_all().unwrap().to_vec1::<f32>().unwrap(), [1.5, 5.5, -5.0]);
    // Refused: a negative or non-finite weight, and any guidance of a model without the pointer.
    let mut bad = config.clone();
    for guidance in [-0.5, f64::NAN, f64::INFINITY] {
        bad.flow.pointer_sharpening = PointerSharpening { guidance, ..PointerSharpening::OFF };
        let message = bad.validate().unwrap_err().to_string();
        assert!(message.contains("flow.pointer_sharpening.guidance"), "{message}");
    }
    let mut no_pointer = tiny_config();
    no_pointer.model.position_pointer = false;
    no_pointer.flow.pointer_weight = 0.0;
    no_pointer.model.relational_pointer = false;
    no_pointer.model.relation_rotation = false;
    no_pointer.validate().unwrap();
    let mut guided_config = no_pointer.clone();
    guided_config.flow.pointer_sharpening.guidance = 2.0;
    let message = guided_config.validate().unwrap_err().to_string();
    assert!(message.contains("guidance") && message.contains("position_pointer"), "{message}");
    let mut plain = Policy::random(&no_pointer, text()).unwrap();
    let options = SamplingOptions {
        sharpening: PointerSharpening { guidance: 2.0, ..PointerSharpening::OFF },
        ..SamplingOptions::new(2, 2, 3)
    };
    let message = plain.predict(&observation, &options).unwrap_err().to_string();
    assert!(message.contains("--pointer-guidance") && message.contains("position_pointer"), "{message}");
}

#[test]
fn the_grounding_loss_needs_the_position_pointer_changes_only_the_total_and_is_learnt() {
    let config = relational_config();
    let mut grounded = config.clone();
    grounded.flow.grounding_weight = 1.0;
    grounded.validate().unwrap();
    // Not serialised when off or at its default radius: configs written before the option are unchanged.
    assert!(serde_json::to_value(&config).unwrap()["flow"].get("grounding_weight").is_none());
    assert!(serde_json::to_value(&grounded).unwrap()["flow"].get("grounding_radius").is_none());
    assert_eq!(serde_json::to_value(&grounded).unwrap()["flow"]["grounding_weight"], 1.0);
    let mut no_pointer = tiny_config();
    (no_pointer.model.position_pointer, no_pointer.flow.pointer_weight) = (false, 0.0);
    no_pointer.flow.grounding_weight = 1.0;
    let err = no_pointer.validate().unwrap_err().to_string();
    assert!(err.contains("flow.grounding_weight") && err.contains("position_pointer"), "{err}");
    for r in [0.0, -0.01, f64::NAN] {
        let mut bad = grounded.clone();
        bad.flow.grounding_radius = r;
        assert!(bad.validate().unwrap_err().to_string().contains("flow.grounding_radius"));
    }
    // The same draws and weights: only the total moves, from the first step on.
    let (plain, with) = (first_step(&config), first_step(&grounded));
    assert!(with.total.is_finite(), "{with:?}");
    assert_eq!((plain.cfm, plain.bce), (with.cfm, with.bce));
    assert_ne!(plain.total, with.total);
    // Trained on the grounding loss alone, the instruction query learns to separate the tokens
    // under the episode's later keyframes from the rest: the loss (ln 2 for a query that does
    // not separate them, ln 2 / 2 if the labels held one class) falls well below it.
    let mut alone = grounded.clone();
    (alone.flow.cfm_weight, alone.flow.open_weight, alone.flow.pointer_weight, alone.flow.goal_weight) =
        (0.0, 0.0, 0.0, 0.0);
    alone.validate().unwrap();
    let mut data = TrainingData::from_episodes(vec![demonstration().clone()]).unwrap();
    let mut text = text();
    let mut trainer = Trainer::new(&alone).unwrap();
    let losses: Vec<f64> = (0..80).map(|_| trainer.train_step(&mut data, &mut text).unwrap().total).collect();
    let (first, last) = (losses[0], losses[70..].iter().sum::<f64>() / 10.0);
    assert!(first > 0.55 && last < 0.5 * first, "grounding loss {first} -> {last}");
}

#[test]
fn instruction_dropout_trains_on_the_null_instruction_from_its_own_stream_and_is_validated() {
    let config = tiny_config();
    let mut dropped = config.clone();
    dropped.flow.instruction_dropout = 0.5;
    dropped.validate().unwrap();
    // Not serialised when 0: configs written before the option are unchanged.
    assert!(serde_json::to_value(&config).unwrap()["flow"].get("instruction_dropout").is_none());
    assert_eq!(serde_json::to_value(&dropped).unwrap()["flow"]["instruction_dropout"], 0.5);
    // Half of a batch of 16 loses its instruction: a different loss from the same draws, and the
    // same loss again from the same seed (the dropout has its own random stream).
    let (plain, once, again) = (first_step(&config), first_step(&dropped), first_step(&dropped));
    assert!(once.total.is_finite(), "{once:?}");
    assert_ne!(plain, once);
    assert_eq!(once, again);
    // On an episode whose instruction is already the null one, dropping it changes nothing, bit
    // for bit: the dropout substitutes exactly the null features and draws from no other stream.
    let mut silent = demonstration().clone();
    silent.instruction = flowram::policy::inputs::NULL_INSTRUCTION.to_string();
    let step_on = |config: &PolicyConfig| {
        let mut data = TrainingData::from_episodes(vec![silent.clone()]).unwrap();
        Trainer::new(config).unwrap().train_step(&mut data, &mut text()).unwrap()
    };
    assert_eq!(step_on(&config), step_on(&dropped));
    // Refused: a probability outside [0, 1).
    for p in [-0.1, 1.0, f64::NAN] {
        let mut bad = config.clone();
        bad.flow.instruction_dropout = p;
        let message = bad.validate().unwrap_err().to_string();
        assert!(message.contains("flow.instruction_dropout"), "{message}");
    }
}
