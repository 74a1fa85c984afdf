//! Where the native dependencies installed by `scripts/setup.sh` live, and the project's own
//! `models/` folder.
//!
//! The dependency folder is `$FLOWRAM_DEPS` when set, else the `.deps/` folder the build saw
//! (baked in by `build.rs`). Every lookup checks that the file is there and otherwise names
//! `scripts/setup.sh`, so a missing setup is a clear error rather than a MuJoCo parse failure.
use std::path::{Path, PathBuf};

/// A dependency the project needs is not where `scripts/setup.sh` puts it.
#[derive(Debug, thiserror::Error)]
#[error("{what} not found at {path}: run scripts/setup.sh (or set FLOWRAM_DEPS to the folder it installed into)")]
pub struct MissingDependency {
    pub what: &'static str,
    pub path: PathBuf,
}

/// The folder that `scripts/setup.sh` installed into.
#[derive(Debug, Clone)]
pub struct Deps {
    root: PathBuf,
}

impl Deps {
    /// `$FLOWRAM_DEPS`, or the `.deps/` folder of the checkout this binary was built from.
    pub fn locate() -> Self {
        let root = std::env::var_os("FLOWRAM_DEPS")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from(env!("FLOWRAM_BUILD_DEPS_DIR")));
        Self { root }
    }

    /// A dependency folder at an explicit path (tests, tools).
    pub fn at(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    fn file(&self, what: &'static str, rel: &str) -> Result<PathBuf, MissingDependency> {
        let path = self.root.join(rel);
        if path.is_file() { Ok(path) } else { Err(MissingDependency { what, path }) }
    }

    /// MJCF of the Franka Panda arm (dm-robotics-panda), meshes beside it.
    pub fn panda_arm_mjcf(&self) -> Result<PathBuf, MissingDependency> {
        self.file("the Franka Panda arm model (panda.xml)", "panda/panda.xml")
    }

    /// MJCF of the Franka hand (dm-robotics-panda), meshes beside it.
    pub fn panda_hand_mjcf(&self) -> Result<PathBuf, MissingDependency> {
        self.file("the Franka hand model (panda_hand.xml)", "panda/panda_hand.xml")
    }

    /// Folder with all-MiniLM-L6-v2's `model.safetensors`, `config.json`, `tokenizer.json`.
    pub fn minilm_dir(&self) -> Result<PathBuf, MissingDependency> {
        self.file("the all-MiniLM-L6-v2 weights", "minilm/model.safetensors")
            .map(|p| p.parent().map(Path::to_path_buf).unwrap_or_default())
    }
}

/// The project's `models/` folder (scene MJCF files): `$FLOWRAM_MODELS` or the checkout's.
pub fn models_dir() -> PathBuf {
    std::env::var_os("FLOWRAM_MODELS")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("models"))
}

/// The project's `controllers/` folder (limits and controller profiles, TOML).
pub fn controllers_dir() -> PathBuf {
    std::env::var_os("FLOWRAM_CONTROLLERS")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("controllers"))
}
