//! Bad input gets a clear error that says what is wrong and what to do, never a panic.
mod common;

use flowram::deps::Deps;
use flowram::sim::{SimError, World};

fn stderr_of(out: &std::process::Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn assert_clean_failure(out: &std::process::Output) -> String {
    let err = stderr_of(out);
    assert_eq!(out.status.code(), Some(1), "exit code 1 for a user error; stderr: {err}");
    assert!(!err.contains("panicked"), "no panic: {err}");
    err
}

#[test]
fn missing_setup_names_the_setup_script() {
    let scene = flowram::sim::scene::resolve_scene("default").unwrap();
    let err = World::load(&scene, &Deps::at("/nonexistent/flowram-deps")).unwrap_err();
    assert!(matches!(err, SimError::MissingDependency(_)));
    assert!(err.to_string().contains("scripts/setup.sh"), "{err}");

    let out = common::flowram()
        .env("FLOWRAM_DEPS", "/nonexistent/flowram-deps")
        .args(["render", "--out", "/tmp/flowram-never-written"])
        .output()
        .unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("scripts/setup.sh"), "{err}");
    assert!(!std::path::Path::new("/tmp/flowram-never-written").exists());
}

#[test]
fn missing_scene_file_names_the_path() {
    let err = World::load_named("/nonexistent/scene.xml").unwrap_err().to_string();
    assert!(err.contains("/nonexistent/scene.xml"), "{err}");
    let err = World::load_named("no_such_scene").unwrap_err().to_string();
    assert!(err.contains("no_such_scene.xml") && err.contains("not found"), "{err}");
}

#[test]
fn malformed_mjcf_gives_mujocos_message_and_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("broken.xml");
    std::fs::write(&path, "<mujoco><worldbody><body></mujoco>").unwrap();
    let err = World::load(&path, &Deps::locate()).unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, SimError::Load { .. }), "{err:?}");
    assert!(text.contains(&path.display().to_string()), "{text}");
    assert!(text.contains("XML"), "MuJoCo's own parser message is kept: {text}");

    let out = common::flowram()
        .args(["render", "--scene"])
        .arg(&path)
        .args(["--out"])
        .arg(dir.path().join("out"))
        .output()
        .unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("broken.xml"), "{err}");
}

#[test]
fn scene_without_the_robot_mount_says_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bare.xml");
    std::fs::write(&path, "<mujoco><worldbody><geom type='plane' size='1 1 1'/></worldbody></mujoco>").unwrap();
    let err = World::load(&path, &Deps::locate()).unwrap_err().to_string();
    assert!(err.contains("panda_mount"), "{err}");
}

#[test]
fn unknown_camera_lists_the_valid_ones() {
    let dir = tempfile::tempdir().unwrap();
    let out = common::flowram().args(["render", "--camera", "top", "--out"]).arg(dir.path()).output().unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("front, left_shoulder, right_shoulder, wrist"), "{err}");
    let out = common::flowram()
        .args(["bench", "render", "--camera", "top", "--frames", "1", "--repeats", "1"])
        .output()
        .unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("front, left_shoulder, right_shoulder, wrist"), "{err}");
}

#[test]
fn image_size_out_of_range_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    for size in ["0", "4096"] {
        let out = common::flowram().args(["render", "--size", size, "--out"]).arg(dir.path()).output().unwrap();
        let err = assert_clean_failure(&out);
        assert!(err.contains("image size") && err.contains("512"), "{err}");
    }
}

/// Writes models/policy/cpu.toml to `path` with its line starting with `key` replaced by `line`.
fn cpu_toml_with(path: &std::path::Path, key: &str, line: &str) {
    let text = std::fs::read_to_string(flowram::deps::models_dir().join("policy/cpu.toml")).unwrap();
    assert!(text.lines().any(|l| l.starts_with(key)), "cpu.toml sets {key}");
    let lines: Vec<&str> = text.lines().map(|l| if l.starts_with(key) { line } else { l }).collect();
    std::fs::write(path, lines.join("\n")).unwrap();
}

#[test]
fn policy_commands_name_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no_run");
    let out = common::flowram()
        .args(["predict", "--checkpoint"])
        .arg(&missing)
        .args(["--episode"])
        .arg(dir.path().join("episode.safetensors"))
        .args(["--keyframe", "0"])
        .output()
        .unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("no_run") && err.contains("no such folder"), "{err}");
    assert!(!missing.exists(), "a failed predict must not create folders");
    let out = common::flowram()
        .args(["train", "--data"])
        .arg(dir.path().join("no_data"))
        .args(["--out"])
        .arg(dir.path().join("run"))
        .output()
        .unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("no_data"), "{err}");
    let bad = dir.path().join("bad.toml");
    cpu_toml_with(&bad, "semantic_tokens", "semantic_tokens = 0");
    let err = flowram::policy::config::PolicyConfig::from_toml_file(&bad).unwrap_err().to_string();
    assert!(err.contains("observation.semantic_tokens") && err.contains("bad.toml"), "{err}");
}

#[test]
fn zero_samples_or_euler_steps_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("no_samples.toml");
    cpu_toml_with(&bad, "consensus_samples", "consensus_samples = 0");
    let err = flowram::policy::config::PolicyConfig::from_toml_file(&bad).unwrap_err().to_string();
    assert!(err.contains("flow.consensus_samples") && err.contains("no_samples.toml"), "{err}");

    // At the command line, before anything is loaded or run: a usage error (exit code 2) that
    // names the option and what it expects.
    let episode = dir.path().join("episode.safetensors");
    let cases: [&[&str]; 5] = [
        &["run", "--task", "open_drawer", "--policy", "flowram", "--samples", "0"],
        &["run", "--task", "open_drawer", "--policy", "flowram", "--steps", "0"],
        &["bench", "success", "--tasks", "open_drawer", "--samples", "0"],
        &["predict", "--checkpoint", "x", "--episode", "y", "--keyframe", "0", "--samples", "0"],
        &["predict", "--checkpoint", "x", "--episode", "y", "--keyframe", "0", "--steps", "1.5"],
    ];
    for args in cases {
        let out = common::flowram().args(args).current_dir(dir.path()).output().unwrap();
        let err = stderr_of(&out);
        assert_eq!(out.status.code(), Some(2), "{args:?}: a usage error; stderr: {err}");
        let option = if args.contains(&"--samples") { "--samples" } else { "--steps" };
        assert!(err.contains(option) && err.contains("at least 1"), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    assert!(!episode.exists() && std::fs::read_dir(dir.path()).unwrap().count() == 1, "nothing written");
}

#[test]
fn closed_loop_commands_name_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    // Without --checkpoint, the shipped checkpoint acts.
    let out = common::flowram()
        .args([
            "run",
            "--task",
            "open_drawer",
            "--policy",
            "flowram",
            "--seed",
            "1000",
            "--max-keyframes",
            "1",
            "--json",
        ])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["keyframes"], 1, "{report}");
    let out =
        common::flowram().args(["run", "--task", "open_drawer", "--checkpoint"]).arg(dir.path()).output().unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("--policy flowram"), "a checkpoint the expert would ignore: {err}");
    let missing = dir.path().join("no_run");
    let out = common::flowram()
        .args(["bench", "success", "--tasks", "open_drawer", "--checkpoint"])
        .arg(&missing)
        .output()
        .unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("no_run") && err.contains("no such folder"), "{err}");
    let out = common::flowram()
        .args(["bench", "success", "--tasks", "juggle", "--checkpoint"])
        .arg(&missing)
        .output()
        .unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("juggle") && err.contains("open_drawer"), "unknown task named before loading anything: {err}");
    // A missing --baseline is named before a single episode runs.
    let out = common::flowram()
        .args(["bench", "success", "--tasks", "open_drawer", "--episodes", "50", "--baseline"])
        .arg(&missing)
        .output()
        .unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("no_run") && err.contains("no such folder"), "{err}");
    let out =
        common::flowram().args(["bench", "success", "--tasks", "open_drawer", "--episodes", "0"]).output().unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("--episodes"), "{err}");
    let out = common::flowram()
        .args(["run", "--task", "open_drawer", "--policy", "flowram", "--max-keyframes", "0", "--checkpoint"])
        .arg(&missing)
        .output()
        .unwrap();
    let err = assert_clean_failure(&out);
    assert!(err.contains("--max-keyframes"), "{err}");
}
