//! Checkpoints of a training run: the model, its EMA and the optimiser turned into named
//! tensors for the [`CheckpointStore`], and a checkpoint restored into them, every file and
//! tensor verified before anything changes (so `--resume` continues exactly).
use std::path::{Path, PathBuf};

use candle_nn::VarMap;

use super::adamw::AdamW;
use super::ema::Ema;
use crate::policy::checkpoint::format::{OPTIMIZER_PREFIX, TrainerState};
use crate::policy::checkpoint::store::{CheckpointStore, CheckpointTensors, read_checkpoint};
use crate::policy::checkpoint::weights::{check_model_tensors, model_device, varmap_tensors};
use crate::policy::error::Result;

/// What [`load_checkpoint`] returns besides filling the model and optimiser.
#[derive(Clone, Debug)]
pub struct LoadedCheckpoint {
    pub dir: PathBuf,
    pub config: serde_json::Value,
    pub trainer: TrainerState,
}

/// Saves the model, EMA and optimiser as the checkpoint of `trainer.step` in `store`.
pub fn save_checkpoint(
    store: &CheckpointStore,
    config: &serde_json::Value,
    model: &VarMap,
    ema: &Ema,
    optimizer: &AdamW,
    trainer: &TrainerState,
) -> Result<PathBuf> {
    let tensors = CheckpointTensors {
        model: varmap_tensors(model)?,
        ema: ema.state_tensors()?,
        optimizer: optimizer.state_tensors(OPTIMIZER_PREFIX)?,
    };
    store.save(config, &tensors, trainer)
}

/// Restores a checkpoint directory into `model`, `ema` and `optimizer` and
/// returns its config and trainer state. Every file is verified (digests,
/// names, shapes) before anything is changed, so on error the model and
/// optimiser are untouched; the error names the offending file.
pub fn load_checkpoint(dir: &Path, model: &VarMap, ema: &mut Ema, optimizer: &mut AdamW) -> Result<LoadedCheckpoint> {
    use crate::policy::checkpoint::format::{EMA_FILE, MODEL_FILE, OPTIMIZER_FILE};
    let stored = read_checkpoint(dir, &model_device(model))?;
    let assignments = check_model_tensors(model, &stored.tensors.model, &[], &dir.join(MODEL_FILE))?;
    let ema_state = ema.stage_state(&stored.tensors.ema, &dir.join(EMA_FILE))?;
    let opt_state = optimizer.stage_state(&stored.tensors.optimizer, OPTIMIZER_PREFIX, &dir.join(OPTIMIZER_FILE))?;
    // Everything checked: install.
    for (var, t) in assignments {
        var.set(&t)?;
    }
    ema.apply_state(ema_state);
    optimizer.apply_state(opt_state);
    Ok(LoadedCheckpoint { dir: stored.dir, config: stored.config, trainer: stored.trainer })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::checkpoint::format::{
        CONFIG_FILE, EMA_FILE, LATEST_FILE, MODEL_FILE, OPTIMIZER_FILE, TRAINER_FILE, read_config_json,
    };
    use crate::policy::checkpoint::store::step_dir_name;
    use crate::policy::checkpoint::weights::{load_model_weights, varmap_tensors};
    use crate::policy::error::PolicyError;
    use crate::policy::training::adamw::AdamWConfig;
    use crate::policy::training::ema::EmaConfig;
    use crate::policy::training::rng::step_rng;
    use candle_core::DType;
    use candle_core::{Device, Tensor};
    use candle_nn::{Init, VarBuilder};
    use std::collections::BTreeMap;
    use std::fs;
    use std::path::PathBuf;

    struct TempDir(PathBuf);
    impl TempDir {
        fn new(tag: &str) -> Self {
            let p = std::env::temp_dir().join(format!("policy_train_ckpt_{tag}_{}", std::process::id()));
            let _ = fs::remove_dir_all(&p);
            fs::create_dir_all(&p).unwrap();
            TempDir(p)
        }
    }
    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = fs::remove_dir_all(&self.0);
        }
    }

    /// A small model: "enc.w" [4, 3], "enc.b" [4] (and optionally "head.w" [2, 4]).
    fn model(extra_head: bool, enc_rows: usize) -> VarMap {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        vb.pp("enc").get_with_hints((enc_rows, 3), "w", Init::Randn { mean: 0.0, stdev: 1.0 }).unwrap();
        vb.pp("enc").get_with_hints(enc_rows, "b", Init::Const(0.1)).unwrap();
        if extra_head {
            vb.pp("head").get_with_hints((2, enc_rows), "w", Init::Const(0.2)).unwrap();
        }
        varmap
    }

    fn train_steps(varmap: &VarMap, opt: &mut AdamW, ema: &mut Ema, n: usize) {
        let w = varmap.data().lock().unwrap()["enc.w"].clone();
        for _ in 0..n {
            let loss = w.as_tensor().sqr().unwrap().sum_all().unwrap();
            opt.backward_step(&loss).unwrap();
            ema.update().unwrap();
        }
    }

    fn snapshot(varmap: &VarMap) -> BTreeMap<String, Vec<f32>> {
        varmap_tensors(varmap)
            .unwrap()
            .into_iter()
            .map(|(k, t)| (k, t.flatten_all().unwrap().to_vec1().unwrap()))
            .collect()
    }

    fn save_one(store: &CheckpointStore, varmap: &VarMap, step: u64) -> (PathBuf, AdamW, Ema) {
        let mut opt = AdamW::new(varmap, AdamWConfig { learning_rate: 0.01, ..Default::default() }).unwrap();
        let mut ema = Ema::new(varmap, EmaConfig::default()).unwrap();
        train_steps(varmap, &mut opt, &mut ema, 3);
        let trainer = TrainerState {
            step,
            seed: 42,
            last_loss: Some(1.5),
            elapsed_seconds: 12.0,
            extra: serde_json::json!({"epoch": 1}),
        };
        let config = serde_json::json!({"model": {"dim": 120}});
        let dir = save_checkpoint(store, &config, varmap, &ema, &opt, &trainer).unwrap();
        (dir, opt, ema)
    }

    fn error_path(err: &PolicyError) -> PathBuf {
        match err {
            PolicyError::File { path, .. } => path.clone(),
            other => panic!("expected a File error, got {other:?}"),
        }
    }

    #[test]
    fn round_trip_restores_everything() {
        let tmp = TempDir::new("roundtrip");
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let saved = model(true, 4);
        let (dir, opt, ema) = save_one(&store, &saved, 3);
        assert_eq!(store.latest().unwrap(), Some(dir.clone()));
        for f in [CONFIG_FILE, MODEL_FILE, EMA_FILE, OPTIMIZER_FILE, TRAINER_FILE] {
            assert!(dir.join(f).is_file(), "{f}");
        }

        let fresh = model(true, 4);
        let mut opt2 = AdamW::new(&fresh, AdamWConfig::default()).unwrap();
        let mut ema2 = Ema::new(&fresh, EmaConfig::default()).unwrap();
        let loaded = load_checkpoint(&dir, &fresh, &mut ema2, &mut opt2).unwrap();
        assert_eq!(loaded.trainer.step, 3);
        assert_eq!(loaded.trainer.seed, 42);
        assert_eq!(loaded.trainer.extra["epoch"], 1);
        assert_eq!(loaded.config["model"]["dim"], 120);
        assert_eq!(snapshot(&fresh), snapshot(&saved));
        assert_eq!(opt2.step_count(), opt.step_count());
        assert_eq!(ema2.updates(), ema.updates());
        let (a, b) = (ema.tensors().unwrap(), ema2.tensors().unwrap());
        assert_eq!(a["enc.w"].to_vec2::<f32>().unwrap(), b["enc.w"].to_vec2::<f32>().unwrap());
        let (a, b) = (opt.state_tensors("x").unwrap(), opt2.state_tensors("x").unwrap());
        assert_eq!(a["xv.enc.w"].to_vec2::<f32>().unwrap(), b["xv.enc.w"].to_vec2::<f32>().unwrap());

        // EMA weights load as a model for inference.
        let inference = model(true, 4);
        load_model_weights(&dir.join(EMA_FILE), &inference).unwrap();
        assert_eq!(
            snapshot(&inference)["enc.w"],
            ema.tensors().unwrap()["enc.w"].flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
        assert_eq!(read_config_json(&dir).unwrap()["model"]["dim"], 120);
    }

    #[test]
    fn truncated_model_file_is_named() {
        let tmp = TempDir::new("truncated");
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let saved = model(false, 4);
        let (dir, _, _) = save_one(&store, &saved, 1);
        let model_path = dir.join(MODEL_FILE);
        let bytes = fs::read(&model_path).unwrap();
        fs::write(&model_path, &bytes[..bytes.len() / 2]).unwrap();

        let fresh = model(false, 4);
        let before = snapshot(&fresh);
        let mut opt = AdamW::new(&fresh, AdamWConfig::default()).unwrap();
        let mut ema = Ema::new(&fresh, EmaConfig::default()).unwrap();
        let err = load_checkpoint(&dir, &fresh, &mut ema, &mut opt).unwrap_err();
        assert_eq!(error_path(&err), model_path);
        assert!(err.to_string().contains("truncated"), "{err}");
        assert_eq!(snapshot(&fresh), before, "a failed load must not change the model");
        assert_eq!(opt.step_count(), 0);

        // Without trainer.json's digests the safetensors parser catches it too.
        let err = load_model_weights(&model_path, &fresh).unwrap_err();
        assert_eq!(error_path(&err), model_path);
        assert!(err.to_string().contains("safetensors"), "{err}");
    }

    #[test]
    fn missing_tensor_and_wrong_shape_are_named() {
        let tmp = TempDir::new("mismatch");
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let saved = model(false, 4);
        let (dir, _, _) = save_one(&store, &saved, 1);
        let model_path = dir.join(MODEL_FILE);

        // The loading model has a head the checkpoint lacks.
        let bigger = model(true, 4);
        let mut opt = AdamW::new(&bigger, AdamWConfig::default()).unwrap();
        let mut ema = Ema::new(&bigger, EmaConfig::default()).unwrap();
        let err = load_checkpoint(&dir, &bigger, &mut ema, &mut opt).unwrap_err();
        assert_eq!(error_path(&err), model_path);
        assert!(err.to_string().contains("missing tensor 'head.w'"), "{err}");

        // Same names, different shape.
        let wider = model(false, 5);
        let mut opt = AdamW::new(&wider, AdamWConfig::default()).unwrap();
        let mut ema = Ema::new(&wider, EmaConfig::default()).unwrap();
        let err = load_checkpoint(&dir, &wider, &mut ema, &mut opt).unwrap_err();
        assert_eq!(error_path(&err), model_path);
        let msg = err.to_string();
        assert!(msg.contains("'enc.b'") && msg.contains("[4]") && msg.contains("[5]"), "{msg}");
    }

    #[test]
    fn corrupted_bytes_are_detected_by_digest() {
        let tmp = TempDir::new("corrupt");
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let saved = model(false, 4);
        let (dir, _, _) = save_one(&store, &saved, 1);
        let opt_path = dir.join(OPTIMIZER_FILE);
        let mut bytes = fs::read(&opt_path).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 0x55;
        fs::write(&opt_path, &bytes).unwrap();
        let fresh = model(false, 4);
        let mut opt = AdamW::new(&fresh, AdamWConfig::default()).unwrap();
        let mut ema = Ema::new(&fresh, EmaConfig::default()).unwrap();
        let err = load_checkpoint(&dir, &fresh, &mut ema, &mut opt).unwrap_err();
        assert_eq!(error_path(&err), opt_path);
        assert!(err.to_string().contains("digest"), "{err}");
    }

    #[test]
    fn interrupted_save_leaves_previous_checkpoint_and_pruning_keeps_newest() {
        let tmp = TempDir::new("interrupt");
        let store = CheckpointStore::open(&tmp.0).unwrap().with_keep_last(2);
        let saved = model(false, 4);
        let (first, _, _) = save_one(&store, &saved, 10);
        // A save killed half-way: a staging directory with some files and a
        // step directory without trainer.json.
        let staging = tmp.0.join(".staging-step-000000020-999-0");
        fs::create_dir_all(&staging).unwrap();
        fs::write(staging.join(MODEL_FILE), b"partial").unwrap();
        let uncommitted = tmp.0.join(step_dir_name(30));
        fs::create_dir_all(&uncommitted).unwrap();
        fs::write(uncommitted.join(MODEL_FILE), b"partial").unwrap();
        assert_eq!(store.latest().unwrap(), Some(first.clone()));
        // Even with the pointer gone, the newest committed one is found.
        fs::remove_file(tmp.0.join(LATEST_FILE)).unwrap();
        assert_eq!(store.latest().unwrap(), Some(first.clone()));

        save_one(&store, &saved, 20);
        assert!(!staging.exists(), "stale staging directories are removed");
        let (third, _, _) = save_one(&store, &saved, 40);
        let steps: Vec<u64> = store.committed().unwrap().into_iter().map(|(s, _)| s).collect();
        assert_eq!(steps, vec![20, 40]);
        assert_eq!(store.latest().unwrap(), Some(third));
        // Saving the same step again replaces it.
        let (again, _, _) = save_one(&store, &saved, 40);
        assert_eq!(store.latest().unwrap(), Some(again));
    }

    /// A miniature FlowRAM training step: image encoder -> pooled features,
    /// concatenated with (a_t, t) -> velocity and open logit; loss of Table B.
    struct MiniPolicy {
        encoder: crate::policy::network::image_encoder::ImageEncoder,
        head: candle_nn::Linear,
    }

    impl MiniPolicy {
        fn new(varmap: &VarMap) -> Self {
            let vb = VarBuilder::from_varmap(varmap, DType::F32, &Device::Cpu);
            let cfg = crate::policy::network::image_encoder::ImageEncoderConfig {
                image_size: 32,
                out_channels: 8,
                widths: vec![8, 12],
                blocks: vec![1, 1],
                ..Default::default()
            };
            let encoder = crate::policy::network::image_encoder::ImageEncoder::new(cfg, vb.pp("encoder")).unwrap();
            let head = candle_nn::linear(
                8 + crate::policy::scene::observation::ACTION_DIMS + 1,
                crate::policy::scene::observation::ACTION_DIMS + 1,
                vb.pp("head"),
            )
            .unwrap();
            Self { encoder, head }
        }

        /// One optimiser step `step` (1-based); returns the total loss.
        #[allow(clippy::too_many_arguments)]
        fn train_step(
            &self,
            images: &Tensor,
            a1: &Tensor,
            open: &Tensor,
            seed: u64,
            step: u64,
            opt: &mut AdamW,
            ema: &mut Ema,
        ) -> f32 {
            use crate::policy::flow::{FlowTimeSampling, LossWeights, flow_matching_loss, flow_training_sample};
            use crate::policy::scene::observation::ACTION_DIMS;
            let mut rng = step_rng(seed, step);
            let sample = flow_training_sample(a1, &mut rng, FlowTimeSampling::Uniform).unwrap();
            let feats = self.encoder.forward_channels_last(images).unwrap().mean((1, 2)).unwrap();
            let input = Tensor::cat(&[&feats, &sample.a_t, &sample.t.unsqueeze(1).unwrap()], 1).unwrap();
            let out = candle_nn::Module::forward(&self.head, &input).unwrap();
            let v_pred = out.narrow(1, 0, ACTION_DIMS).unwrap();
            let open_logit = out.narrow(1, ACTION_DIMS, 1).unwrap().squeeze(1).unwrap();
            let (total, _, _) =
                flow_matching_loss(&v_pred, &sample.target_velocity, &open_logit, open, &LossWeights::default())
                    .unwrap();
            opt.backward_step(&total).unwrap();
            ema.update().unwrap();
            total.to_scalar::<f32>().unwrap()
        }
    }

    #[test]
    fn resumed_training_is_bit_identical_to_uninterrupted() {
        let tmp = TempDir::new("resume");
        let dev = Device::Cpu;
        let images = Tensor::from_vec(
            (0..4 * 3 * 32 * 32).map(|i| ((i * 37) % 251) as u8).collect::<Vec<u8>>(),
            (4, 3, 32, 32),
            &dev,
        )
        .unwrap();
        let a1 = Tensor::randn(0f32, 0.5, (4, crate::policy::scene::observation::ACTION_DIMS), &dev).unwrap();
        let open = Tensor::new(&[1f32, 0.0, 1.0, 0.0], &dev).unwrap();
        let seed = 1234;
        let opt_cfg = AdamWConfig { learning_rate: 1e-3, max_grad_norm: Some(1.0), ..Default::default() };

        // Two runs from the same initial weights.
        let vm_a = VarMap::new();
        let policy_a = MiniPolicy::new(&vm_a);
        let vm_b = VarMap::new();
        let policy_b = MiniPolicy::new(&vm_b);
        copy_weights(&vm_a, &vm_b);

        // Uninterrupted: 6 steps.
        let mut opt_a = AdamW::new(&vm_a, opt_cfg.clone()).unwrap();
        let mut ema_a = Ema::new(&vm_a, EmaConfig::default()).unwrap();
        let losses_a: Vec<f32> =
            (1..=6).map(|s| policy_a.train_step(&images, &a1, &open, seed, s, &mut opt_a, &mut ema_a)).collect();

        // Interrupted: 3 steps, checkpoint, "crash".
        let mut opt_b = AdamW::new(&vm_b, opt_cfg.clone()).unwrap();
        let mut ema_b = Ema::new(&vm_b, EmaConfig::default()).unwrap();
        let mut last = 0.0;
        for s in 1..=3 {
            last = policy_b.train_step(&images, &a1, &open, seed, s, &mut opt_b, &mut ema_b);
        }
        let store = CheckpointStore::open(&tmp.0).unwrap();
        let trainer = TrainerState {
            step: 3,
            seed,
            last_loss: Some(last as f64),
            elapsed_seconds: 0.0,
            extra: serde_json::Value::Null,
        };
        save_checkpoint(&store, &serde_json::json!({}), &vm_b, &ema_b, &opt_b, &trainer).unwrap();
        drop((policy_b, opt_b, ema_b, vm_b));

        // Fresh process: new (differently initialised) model, resume.
        let vm_c = VarMap::new();
        let policy_c = MiniPolicy::new(&vm_c);
        let mut opt_c = AdamW::new(&vm_c, opt_cfg).unwrap();
        let mut ema_c = Ema::new(&vm_c, EmaConfig::default()).unwrap();
        let loaded = load_checkpoint(&store.latest().unwrap().unwrap(), &vm_c, &mut ema_c, &mut opt_c).unwrap();
        let losses_c: Vec<f32> = (loaded.trainer.step + 1..=6)
            .map(|s| policy_c.train_step(&images, &a1, &open, loaded.trainer.seed, s, &mut opt_c, &mut ema_c))
            .collect();

        assert_eq!(losses_c, losses_a[3..].to_vec());
        assert_eq!(snapshot(&vm_c), snapshot(&vm_a));
        let (ea, ec) = (ema_a.tensors().unwrap(), ema_c.tensors().unwrap());
        for (name, t) in &ea {
            let a: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            let c: Vec<f32> = ec[name].flatten_all().unwrap().to_vec1().unwrap();
            assert_eq!(a, c, "EMA {name}");
        }
    }

    /// Copies `from`'s weights into `to` (same structure).
    fn copy_weights(from: &VarMap, to: &VarMap) {
        let src = from.data().lock().unwrap();
        for (name, var) in to.data().lock().unwrap().iter() {
            var.set(src[name].as_tensor()).unwrap();
        }
    }
}
