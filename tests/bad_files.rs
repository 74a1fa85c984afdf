//! The bad-file corpus: every file flowram reads (keyframes JSON, controller and collision
//! TOML, joint limits, policy configs, dataset index and episodes, checkpoints), each mangled
//! by hand-written cases and by seeded generated mutations (truncation, bit flips, wrong types,
//! NaN and infinite numbers, unknown fields, wrong shapes). Every case must end in an error that
//! names the file (and, for the mutations that target one value, the field or the line), never
//! in a panic, and never load as something else: a mutation that must be refused is never
//! accepted, and the binary formats (episodes, checkpoints) carry digests, so no changed byte
//! loads. Loading never writes: the files on disk are left as they were.
mod common;

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

use flowram::control::keyframe::KeyframeFile;
use flowram::control::osc_config::OscConfig;
use flowram::data::{load_dataset, read_index};
use flowram::franka::collision::CollisionProfile;
use flowram::policy::config::PolicyConfig;
use flowram::robot::JointLimits;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// How a mutation must be received.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Expect {
    /// Refused with an error naming the file (and the case's `needle`, if it has one: the
    /// field's name or its line).
    Refused,
    /// Either refused (naming the file) or accepted: a text edit that can leave a valid file
    /// (a flipped digit is another valid number).
    Either,
}

struct Case {
    what: String,
    bytes: Vec<u8>,
    expect: Expect,
    needle: Option<String>,
}

/// Loads `path` with `load`; panics are caught and reported as failures of the case.
fn check(
    label: &str,
    path: &Path,
    cases: Vec<Case>,
    load: &dyn Fn(&Path) -> Result<(), String>,
    failures: &mut Vec<String>,
) -> usize {
    let original = std::fs::read(path).unwrap();
    let name = path.file_name().unwrap().to_string_lossy().into_owned();
    let n = cases.len();
    for case in cases {
        std::fs::write(path, &case.bytes).unwrap();
        let outcome = catch_unwind(AssertUnwindSafe(|| load(path)));
        let on_disk = std::fs::read(path).unwrap();
        let tag = format!("{label}: {}", case.what);
        if on_disk != case.bytes {
            failures.push(format!("{tag}: loading changed the file on disk"));
        }
        match (outcome, case.expect) {
            (Err(_), _) => failures.push(format!("{tag}: PANICKED")),
            (Ok(Ok(())), Expect::Either) => {}
            (Ok(Ok(())), _) => failures.push(format!("{tag}: accepted, must be refused")),
            (Ok(Err(message)), _) => {
                if !message.contains(&name) {
                    failures.push(format!("{tag}: the error does not name {name}: {message}"));
                }
                if let Some(needle) = &case.needle
                    && !message.contains(needle.as_str())
                {
                    failures.push(format!("{tag}: the error does not name `{needle}`: {message}"));
                }
            }
        }
    }
    std::fs::write(path, original).unwrap();
    n
}

/// Truncations at seeded points and single-bit flips.
fn byte_mutations(bytes: &[u8], rng: &mut ChaCha8Rng, binary_checked: bool) -> Vec<Case> {
    let expect = if binary_checked { Expect::Refused } else { Expect::Either };
    let mut cases = vec![Case { what: "empty".into(), bytes: Vec::new(), expect: Expect::Refused, needle: None }];
    for _ in 0..6 {
        let at = rng.random_range(0..bytes.len());
        cases.push(Case { what: format!("truncated at byte {at}"), bytes: bytes[..at].to_vec(), expect, needle: None });
    }
    for _ in 0..10 {
        let (at, bit) = (rng.random_range(0..bytes.len()), rng.random_range(0..8));
        let mut b = bytes.to_vec();
        b[at] ^= 1 << bit;
        cases.push(Case { what: format!("bit {bit} of byte {at} flipped"), bytes: b, expect, needle: None });
    }
    cases
}

/// Numbers of a JSON or TOML text outside comments and strings: (start, end, key of the line or
/// the nearest JSON key before it).
fn number_spans(text: &str, toml: bool) -> Vec<(usize, usize, String)> {
    let bytes = text.as_bytes();
    let mut spans = Vec::new();
    let (mut in_string, mut in_comment) = (false, false);
    let mut key = String::new();
    let mut line_start = 0;
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        if c == b'\n' {
            in_comment = false;
            line_start = i + 1;
        }
        if in_comment {
            i += 1;
            continue;
        }
        if c == b'"' {
            if !in_string && !toml {
                // a JSON key: "name":
                let end = text[i + 1..].find('"').map_or(i, |e| i + 1 + e);
                if text[end + 1..].trim_start().starts_with(':') {
                    key = text[i + 1..end].to_string();
                }
            }
            in_string = !in_string;
        } else if !in_string && toml && c == b'#' {
            in_comment = true;
        } else if !in_string && (c.is_ascii_digit() || c == b'-') {
            let prev = if i == 0 { b' ' } else { bytes[i - 1] };
            if matches!(prev, b' ' | b'[' | b',' | b'=' | b':' | b'\t') {
                let end = text[i..]
                    .find(|ch: char| !(ch.is_ascii_digit() || matches!(ch, '.' | 'e' | 'E' | '-' | '+' | '_')))
                    .map_or(text.len(), |e| i + e);
                if toml {
                    key = text[line_start..].split('=').next().unwrap_or("").trim().to_string();
                }
                if end > i && text[i..end].chars().any(|ch| ch.is_ascii_digit()) {
                    spans.push((i, end, key.clone()));
                }
                i = end;
                continue;
            }
        }
        i += 1;
    }
    spans
}

/// Structured mutations of a text format: each must be refused.
fn text_mutations(text: &str, toml: bool, rng: &mut ChaCha8Rng, name_fields: bool) -> Vec<Case> {
    let spans = number_spans(text, toml);
    assert!(!spans.is_empty(), "no numbers found");
    let mut cases = Vec::new();
    let replacements: &[&str] = if toml {
        &["nan", "inf", "-inf", "1e999", "\"text\"", "true"]
    } else {
        &["NaN", "1e999", "\"text\"", "true", "null"]
    };
    for _ in 0..8 {
        let (start, end, key) = spans[rng.random_range(0..spans.len())].clone();
        let with = replacements[rng.random_range(0..replacements.len())];
        let bytes = format!("{}{}{}", &text[..start], with, &text[end..]).into_bytes();
        let needle = (name_fields && !key.is_empty()).then(|| key.rsplit('.').next().unwrap_or(&key).to_string());
        cases.push(Case {
            what: format!("`{key}` value {} -> {with}", &text[start..end]),
            bytes,
            expect: Expect::Refused,
            needle,
        });
    }
    // wrong shape: one value fewer in an array of numbers
    let shortened = spans.iter().find_map(|(start, end, key)| {
        let after = &text[*end..];
        after.trim_start().starts_with(',').then(|| {
            let comma = end + after.find(',').unwrap();
            (format!("{}{}", &text[..*start], &text[comma + 1..].trim_start()), key.clone())
        })
    });
    if let Some((shorter, key)) = shortened {
        let needle = (name_fields && !key.is_empty()).then(|| key.rsplit('.').next().unwrap_or(&key).to_string());
        cases.push(Case {
            what: format!("`{key}` array one element short"),
            bytes: shorter.into_bytes(),
            expect: Expect::Refused,
            needle,
        });
    }
    // unknown field
    let unknown = if toml {
        format!("bogus_field = 1\n{text}")
    } else {
        let brace = text.find('{').unwrap();
        format!("{}{{\"bogus_field\": 1, {}", &text[..brace], &text[brace + 1..])
    };
    cases.push(Case {
        what: "an unknown field".into(),
        bytes: unknown.into_bytes(),
        expect: Expect::Refused,
        needle: Some("bogus_field".into()),
    });
    cases
}

fn all_mutations(path: &Path, toml: bool, seed: u64, name_fields: bool) -> Vec<Case> {
    let bytes = std::fs::read(path).unwrap();
    let text = String::from_utf8(bytes.clone()).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut cases = byte_mutations(&bytes, &mut rng, false);
    cases.extend(text_mutations(&text, toml, &mut rng, name_fields));
    cases
}

fn copy_into(dir: &Path, from: &Path) -> PathBuf {
    let to = dir.join(from.file_name().unwrap());
    std::fs::copy(from, &to).unwrap();
    to
}

fn report(failures: &[String], cases: usize) {
    assert!(failures.is_empty(), "{} of {cases} bad-file cases failed:\n{}", failures.len(), failures.join("\n"));
}

#[test]
fn configs_and_keyframes_refuse_every_mutation_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let controllers = flowram::deps::controllers_dir();
    let mut failures = Vec::new();
    let mut cases = 0;

    let keyframes = dir.path().join("keyframes.json");
    std::fs::write(
        &keyframes,
        r#"{"keyframes": [{"position": [0.5, 0.0, 0.4], "quat_wxyz": [0.0, 1.0, 0.0, 0.0], "gripper_open": true},
                          {"position": [0.5, 0.1, 0.3], "quat_wxyz": [0.0, 1.0, 0.0, 0.0], "gripper_open": false}]}"#,
    )
    .unwrap();
    let load_keyframes = |p: &Path| KeyframeFile::read(p).map(|_| ()).map_err(|e| e.to_string());
    let mut hand_written = all_mutations(&keyframes, false, 1, true);
    for (what, text) in [
        ("no keyframes", r#"{"keyframes": []}"#),
        ("a list instead of the object", r#"[{"position": [0.5, 0, 0.4]}]"#),
        ("a missing quaternion", r#"{"keyframes": [{"position": [0.5, 0, 0.4], "gripper_open": true}]}"#),
    ] {
        hand_written.push(Case { what: what.into(), bytes: text.into(), expect: Expect::Refused, needle: None });
    }
    cases += check("keyframes", &keyframes, hand_written, &load_keyframes, &mut failures);

    for (file, load, seed) in [
        (
            "osc.toml",
            &(|p: &Path| OscConfig::load(p).map(|_| ()).map_err(|e| e.to_string()))
                as &dyn Fn(&Path) -> Result<(), String>,
            2,
        ),
        ("panda_limits.toml", &|p: &Path| JointLimits::load(p).map(|_| ()).map_err(|e| e.to_string()), 3),
        ("fr3_limits.toml", &|p: &Path| JointLimits::load(p).map(|_| ()).map_err(|e| e.to_string()), 4),
        ("franka_collision.toml", &|p: &Path| CollisionProfile::load(p).map(|_| ()).map_err(|e| e.to_string()), 5),
    ] {
        let path = copy_into(dir.path(), &controllers.join(file));
        let mutations = all_mutations(&path, true, seed, true);
        cases += check(file, &path, mutations, load, &mut failures);
    }
    let policy = copy_into(dir.path(), &flowram::deps::models_dir().join("policy/cpu.toml"));
    let load_policy = |p: &Path| PolicyConfig::from_toml_file(p).map(|_| ()).map_err(|e| e.to_string());
    let mutations = all_mutations(&policy, true, 6, true);
    cases += check("policy config", &policy, mutations, &load_policy, &mut failures);
    report(&failures, cases);
}

#[test]
fn datasets_and_checkpoints_refuse_every_mutation_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let out = common::flowram()
        .args(["collect", "--task", "open_drawer", "--episodes", "1", "--seed", "0", "--cameras", "front"])
        .args(["--size", "32", "--out"])
        .arg(&data)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let mut failures = Vec::new();
    let mut cases = 0;

    // The index: a text format; a bad index is an error, a bad entry a listed failure.
    let load_dataset_strictly = |dir: &Path| -> Result<(), String> {
        let loaded = load_dataset(dir).map_err(|e| e.to_string())?;
        match loaded.failures.first() {
            Some((_, e)) => Err(e.to_string()),
            None => Ok(()),
        }
    };
    let index = data.join("index.json");
    let mutations = all_mutations(&index, false, 7, false);
    cases += check(
        "dataset index",
        &index,
        mutations,
        &|p: &Path| read_index(p.parent().unwrap()).map(|_| ()).map_err(|e| e.to_string()),
        &mut failures,
    );
    // The episode: binary, digested in the index, so every changed byte is refused.
    let episode = data.join(&read_index(&data).unwrap().episodes[0].file);
    let bytes = std::fs::read(&episode).unwrap();
    let mutations = byte_mutations(&bytes, &mut ChaCha8Rng::seed_from_u64(8), true);
    cases +=
        check("episode", &episode, mutations, &|p: &Path| load_dataset_strictly(p.parent().unwrap()), &mut failures);

    // A checkpoint: a short training run, then every file of its newest checkpoint.
    let mut config = common::tiny_policy_config();
    config.observation.image_size = 32;
    config.observation.cameras = vec!["front".into()];
    config.train.steps = 2;
    config.train.checkpoint_every = 2;
    let config_file = dir.path().join("tiny.toml");
    std::fs::write(&config_file, toml::to_string(&config).unwrap()).unwrap();
    let run = dir.path().join("run");
    let out = common::flowram()
        .arg("train")
        .arg("--data")
        .arg(&data)
        .arg("--out")
        .arg(&run)
        .arg("--config")
        .arg(&config_file)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let checkpoint = run.join("checkpoints/step-000000002");
    let load_policy = |p: &Path| {
        let text = flowram::policy::network::text_encoder::TextEncoder::load_installed().unwrap();
        flowram::policy::inference::Policy::load(p.parent().unwrap(), text).map(|_| ()).map_err(|e| e.to_string())
    };
    let load_checkpoint = |p: &Path| {
        flowram::policy::checkpoint::store::read_checkpoint(p.parent().unwrap(), &candle_core::Device::Cpu)
            .map(|_| ())
            .map_err(|e| e.to_string())
    };
    for (file, seed) in [("config.json", 9), ("ema.safetensors", 10), ("trainer.json", 11)] {
        let path = checkpoint.join(file);
        let bytes = std::fs::read(&path).unwrap();
        // digests make every byte count, text or not
        let mut mutations = byte_mutations(&bytes, &mut ChaCha8Rng::seed_from_u64(seed), true);
        if file == "trainer.json" {
            // its own bytes are not digested: a flipped digit may be another valid step count
            mutations.iter_mut().for_each(|m| m.expect = Expect::Either);
        }
        cases += check(&format!("checkpoint {file} (policy)"), &path, mutations, &load_policy, &mut failures);
    }
    for (file, seed) in [("model.safetensors", 12), ("optimizer.safetensors", 13)] {
        let path = checkpoint.join(file);
        let bytes = std::fs::read(&path).unwrap();
        let mutations = byte_mutations(&bytes, &mut ChaCha8Rng::seed_from_u64(seed), true);
        cases += check(&format!("checkpoint {file} (resume)"), &path, mutations, &load_checkpoint, &mut failures);
    }
    report(&failures, cases);
}
