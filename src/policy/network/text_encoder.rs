//! The frozen instruction encoder: all-MiniLM-L6-v2 (6-layer BERT, hidden size 384) through
//! candle-transformers' BERT and the `tokenizers` crate, with a per-instruction cache.
//!
//! The policy reads two things from an instruction: the per-token last hidden states (projected
//! to the model width C elsewhere, as the language tokens of FlowRAM) and a sentence embedding
//! (mean pooling over the tokens, then L2 normalisation, as sentence-transformers does). The
//! encoder is never trained, so each distinct instruction is encoded once and cached.
//!
//! Tokenisation: `tokenizer.json` of the model pads and truncates to 128 tokens; here padding is
//! turned off (one sentence at a time needs no mask: every token is real) and truncation is set to
//! sentence-transformers' `max_seq_length` of 256 tokens.
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use candle_transformers::models::bert::{BertModel, Config};
use tokenizers::{Tokenizer, TruncationParams};

use crate::policy::error::{PolicyError, Result};

/// Width of all-MiniLM-L6-v2's hidden states and sentence embedding.
pub const TEXT_HIDDEN_SIZE: usize = 384;

/// Longest token sequence kept (sentence-transformers' `max_seq_length` for this model).
pub const MAX_INSTRUCTION_TOKENS: usize = 256;

/// Files of the model directory that [`TextEncoder::load`] reads.
pub const MODEL_FILES: [&str; 3] = ["config.json", "tokenizer.json", "model.safetensors"];

/// What the frozen text encoder gives for one instruction.
#[derive(Debug, Clone)]
pub struct InstructionFeatures {
    /// `[T, 384]` f32 on the encoder's device: the last hidden state of every token, `[CLS]` first
    /// and `[SEP]` last (T = word pieces + 2).
    pub tokens: Tensor,
    /// 384 values: the mean of `tokens` over T, L2-normalised (sentence-transformers' embedding).
    pub embedding: Vec<f32>,
}

/// all-MiniLM-L6-v2 on CPU with a cache of encoded instructions.
pub struct TextEncoder {
    model: BertModel,
    tokenizer: Tokenizer,
    device: Device,
    cache: HashMap<String, Arc<InstructionFeatures>>,
}

impl std::fmt::Debug for TextEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TextEncoder").field("cached_instructions", &self.cache.len()).finish_non_exhaustive()
    }
}

fn missing_model_file(path: PathBuf, what: &str) -> PolicyError {
    PolicyError::File {
        path,
        message: format!("{what} (all-MiniLM-L6-v2 instruction encoder); run scripts/setup.sh to install it"),
    }
}

impl TextEncoder {
    /// Loads the weights `scripts/setup.sh` installed (`.deps/minilm`, or under `FLOWRAM_DEPS`).
    ///
    /// Errors: [`PolicyError::MissingDependency`] (with what to run) when they are not there.
    pub fn load_installed() -> Result<Self> {
        Self::load(&crate::deps::Deps::locate().minilm_dir()?)
    }

    /// Loads all-MiniLM-L6-v2 from `dir` (the folder holding `config.json`, `tokenizer.json` and
    /// `model.safetensors`, e.g. `.deps/minilm`) onto the CPU.
    ///
    /// Errors: [`PolicyError::File`] naming the first file that is missing, unreadable or
    /// malformed.
    pub fn load(dir: &Path) -> Result<Self> {
        for name in MODEL_FILES {
            let path = dir.join(name);
            if !path.is_file() {
                return Err(missing_model_file(path, "missing"));
            }
        }
        let device = Device::Cpu;

        let config_path = dir.join("config.json");
        let config_text = std::fs::read_to_string(&config_path)
            .map_err(|e| missing_model_file(config_path.clone(), &format!("unreadable: {e}")))?;
        let config: Config = serde_json::from_str(&config_text)
            .map_err(|e| missing_model_file(config_path.clone(), &format!("not a BERT config: {e}")))?;
        if config.hidden_size != TEXT_HIDDEN_SIZE {
            return Err(missing_model_file(
                config_path,
                &format!("hidden_size {} where all-MiniLM-L6-v2 has {TEXT_HIDDEN_SIZE}", config.hidden_size),
            ));
        }

        let tokenizer_path = dir.join("tokenizer.json");
        let mut tokenizer = Tokenizer::from_file(&tokenizer_path)
            .map_err(|e| missing_model_file(tokenizer_path.clone(), &format!("not a readable tokenizer: {e}")))?;
        tokenizer.with_padding(None);
        tokenizer
            .with_truncation(Some(TruncationParams {
                max_length: MAX_INSTRUCTION_TOKENS.min(config.max_position_embeddings),
                ..Default::default()
            }))
            .map_err(|e| missing_model_file(tokenizer_path, &format!("truncation rejected: {e}")))?;

        let weights_path = dir.join("model.safetensors");
        let weights = std::fs::read(&weights_path)
            .map_err(|e| missing_model_file(weights_path.clone(), &format!("unreadable: {e}")))?;
        let vb = VarBuilder::from_buffered_safetensors(weights, DType::F32, &device)
            .map_err(|e| missing_model_file(weights_path.clone(), &format!("not a safetensors file: {e}")))?;
        let model = BertModel::load(vb, &config)
            .map_err(|e| missing_model_file(weights_path, &format!("weights do not match config.json: {e}")))?;

        Ok(Self { model, tokenizer, device, cache: HashMap::new() })
    }

    /// The device the features live on (CPU).
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Number of distinct instructions encoded so far.
    pub fn cached_instructions(&self) -> usize {
        self.cache.len()
    }

    /// Encodes `instruction` (or returns the cached features of an identical string: the same
    /// `Arc`). Errors: [`PolicyError::Invalid`] when the tokenizer rejects the text.
    pub fn encode(&mut self, instruction: &str) -> Result<Arc<InstructionFeatures>> {
        if let Some(features) = self.cache.get(instruction) {
            return Ok(Arc::clone(features));
        }
        let features = Arc::new(self.encode_uncached(instruction)?);
        self.cache.insert(instruction.to_owned(), Arc::clone(&features));
        Ok(features)
    }

    /// Runs tokenizer and BERT without touching the cache.
    fn encode_uncached(&self, instruction: &str) -> Result<InstructionFeatures> {
        let encoding = self
            .tokenizer
            .encode(instruction, true)
            .map_err(|e| PolicyError::Invalid(format!("cannot tokenize instruction {instruction:?}: {e}")))?;
        let ids = encoding.get_ids();
        let n_tokens = ids.len();
        let input_ids = Tensor::from_slice(ids, (1, n_tokens), &self.device)?;
        let type_ids = Tensor::from_slice(encoding.get_type_ids(), (1, n_tokens), &self.device)?;
        // No padding: every position is a real token, so the mask is all ones.
        let tokens = self.model.forward(&input_ids, &type_ids, None)?.squeeze(0)?; // [T, 384]
        let mean = tokens.mean(0)?.to_vec1::<f32>()?;
        let norm = mean.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        let embedding = mean.iter().map(|v| v / norm).collect();
        Ok(InstructionFeatures { tokens, embedding })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model_dir() -> PathBuf {
        crate::deps::Deps::locate().minilm_dir().expect("run scripts/setup.sh")
    }

    #[test]
    fn embedding_matches_sentence_transformers() {
        let mut encoder = TextEncoder::load(&model_dir()).expect("run scripts/setup.sh");
        let features = encoder.encode("open the top drawer").unwrap();
        let expected = [-0.019867f32, 0.006068, -0.039564, -0.004656, -0.005782];
        for (i, (got, want)) in features.embedding.iter().zip(expected).enumerate() {
            assert!((got - want).abs() < 1e-5, "embedding[{i}] = {got}, expected {want}");
        }
        assert_eq!(features.embedding.len(), TEXT_HIDDEN_SIZE);
        let norm: f32 = features.embedding.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-5);
        // [CLS] open the top drawer [SEP]
        assert_eq!(features.tokens.dims(), &[6, TEXT_HIDDEN_SIZE]);
    }

    #[test]
    fn cache_returns_the_same_features() {
        let mut encoder = TextEncoder::load(&model_dir()).unwrap();
        let a = encoder.encode("close the jar").unwrap();
        let b = encoder.encode("close the jar").unwrap();
        assert!(Arc::ptr_eq(&a, &b));
        let c = encoder.encode("close the red jar").unwrap();
        assert!(!Arc::ptr_eq(&a, &c));
        assert_eq!(encoder.cached_instructions(), 2);
    }

    #[test]
    fn missing_directory_names_the_file_and_the_fix() {
        let err = TextEncoder::load(Path::new("/nonexistent/minilm")).unwrap_err();
        match &err {
            PolicyError::File { path, message } => {
                assert_eq!(path, Path::new("/nonexistent/minilm/config.json"));
                assert!(message.contains("scripts/setup.sh"), "{message}");
            }
            other => panic!("expected a File error, got {other:?}"),
        }
        assert!(err.to_string().contains("/nonexistent/minilm/config.json"));
        assert!(err.to_string().contains("missing"), "{err}");
    }

    #[test]
    fn incomplete_or_corrupt_model_directories_name_the_bad_file() {
        let dir = std::env::temp_dir().join(format!("policy_geo_minilm_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::copy(model_dir().join("config.json"), dir.join("config.json")).unwrap();
        let err = TextEncoder::load(&dir).unwrap_err();
        assert!(matches!(&err, PolicyError::File { path, .. } if path.ends_with("tokenizer.json")), "{err}");
        std::fs::copy(model_dir().join("tokenizer.json"), dir.join("tokenizer.json")).unwrap();
        std::fs::write(dir.join("model.safetensors"), b"not a safetensors file").unwrap();
        let err = TextEncoder::load(&dir).unwrap_err();
        assert!(matches!(&err, PolicyError::File { path, .. } if path.ends_with("model.safetensors")), "{err}");
        assert!(err.to_string().contains("scripts/setup.sh"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
