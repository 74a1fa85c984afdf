//! Shared helpers of the integration tests: scenes with extra objects, built from the real
//! `models/scene.xml` and loaded with the real MuJoCo and the installed Panda model.
#![allow(dead_code)]

use std::path::PathBuf;

use flowram::deps::{Deps, models_dir};
use flowram::sim::World;

/// A copy of `models/scene.xml` with `extra` inserted into its worldbody, in a temp folder.
pub struct TempScene {
    pub dir: tempfile::TempDir,
    pub path: PathBuf,
}

pub fn scene_with(extra_worldbody: &str) -> TempScene {
    let base = std::fs::read_to_string(models_dir().join("scene.xml")).expect("models/scene.xml is readable");
    let xml = base.replacen("</worldbody>", &format!("{extra_worldbody}\n  </worldbody>"), 1);
    assert_ne!(xml, base, "scene.xml has a </worldbody>");
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("scene.xml");
    std::fs::write(&path, xml).expect("write temp scene");
    TempScene { dir, path }
}

pub fn load(scene: &TempScene) -> World {
    World::load(&scene.path, &Deps::locate()).expect("test scene loads")
}

/// The `flowram` binary built for these tests.
pub fn flowram() -> std::process::Command {
    std::process::Command::new(env!("CARGO_BIN_EXE_flowram"))
}

/// The CPU config shrunk for tests that run a (random-weight) policy closed loop: 48 px images,
/// 128 semantic and 32 geometric tokens, one Mamba layer.
pub fn tiny_policy_config() -> flowram::policy::config::PolicyConfig {
    let mut config = flowram::policy::config::PolicyConfig::cpu_default().unwrap();
    config.observation.image_size = 48;
    config.observation.semantic_tokens = 128;
    config.observation.geometric_tokens = 32;
    config.observation.min_inside = 8;
    config.model.layers = 1;
    config.validate().unwrap();
    config
}
