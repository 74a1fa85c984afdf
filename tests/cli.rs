//! The CLI writes what it says, in the documented formats.
mod common;

use std::io::Read;

fn decode_png(path: &std::path::Path) -> (png::OutputInfo, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info, buf)
}

#[test]
fn render_writes_images_clouds_and_camera_models() {
    let dir = tempfile::tempdir().unwrap();
    let out = common::flowram().args(["render", "--size", "64", "--json", "--out"]).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).expect("--json prints one JSON object");
    assert_eq!(report["cameras"].as_array().unwrap().len(), 4);
    assert!(report["seconds"].as_f64().unwrap() > 0.0);
    let files: Vec<String> =
        report["files"].as_array().unwrap().iter().map(|f| f.as_str().unwrap().to_owned()).collect();
    assert_eq!(files.len(), 4 * 4 + 1, "4 files per camera + merged.ply");

    for camera in ["front", "left_shoulder", "right_shoulder", "wrist"] {
        let cam_dir = dir.path().join(camera);
        let (info, rgb) = decode_png(&cam_dir.join("rgb.png"));
        assert_eq!(
            (info.width, info.height, info.color_type, info.bit_depth),
            (64, 64, png::ColorType::Rgb, png::BitDepth::Eight)
        );
        assert!(rgb.iter().any(|&c| c != rgb[0]));
        let (info, depth) = decode_png(&cam_dir.join("depth.png"));
        assert_eq!((info.color_type, info.bit_depth), (png::ColorType::Grayscale, png::BitDepth::Sixteen));
        let mm: Vec<u16> = depth.chunks(2).map(|b| u16::from_be_bytes([b[0], b[1]])).collect();
        let valid: Vec<u16> = mm.iter().copied().filter(|&d| d > 0).collect();
        assert!(valid.len() > 64 * 64 / 2, "{camera}: most pixels have depth");
        assert!(valid.iter().all(|&d| (50..5000).contains(&d)), "{camera}: depths in millimetres of a table scene");

        let mut ply = Vec::new();
        std::fs::File::open(cam_dir.join("cloud.ply")).unwrap().read_to_end(&mut ply).unwrap();
        let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let header = std::str::from_utf8(&ply[..header_end]).unwrap();
        let n: usize = header.lines().find_map(|l| l.strip_prefix("element vertex ")).unwrap().parse().unwrap();
        assert_eq!(n, valid.len(), "{camera}: one point per pixel with depth");
        assert_eq!(ply.len() - header_end, n * 15, "{camera}: 3 floats + 3 bytes per point");

        let model: serde_json::Value =
            serde_json::from_slice(&std::fs::read(cam_dir.join("camera.json")).unwrap()).unwrap();
        assert_eq!(model["intrinsics"][0][2].as_f64(), Some(31.5));
        assert_eq!(model["extrinsics"][3][3].as_f64(), Some(1.0));
    }
}

#[test]
fn benchmarks_print_their_figures_as_json() {
    let out = common::flowram().args(["bench", "sim", "--steps", "500", "--repeats", "1", "--json"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let sim: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(sim["steps_per_s"].as_f64().unwrap() > 0.0);
    assert!(sim["realtime_factor"].as_f64().unwrap() > 0.0);

    let out = common::flowram()
        .args(["bench", "render", "--frames", "3", "--repeats", "1", "--size", "32", "--json"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let render: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(render["size"].as_u64(), Some(32));
    assert_eq!(render["cameras"].as_u64(), Some(1));
    assert!(render["frames_per_s"].as_f64().unwrap() > 0.0);

    let out = common::flowram().args(["bench", "control", "--keyframes", "2", "--json"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let control: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in [
        "tick_us_p50",
        "tick_us_p99",
        "tick_us_max",
        "osc_us_p99",
        "trajectory_us_p99",
        "kinematics_us_p99",
        "ik_ms_median",
        "realtime_factor",
    ] {
        assert!(control[key].as_f64().is_some_and(|v| v > 0.0), "{key} in {control}");
    }
    assert_eq!(control["keyframes_reached"], 2);
}

#[test]
fn track_reports_keyframes_and_logs_every_tick() {
    let dir = tempfile::tempdir().unwrap();
    let keyframes = dir.path().join("keyframes.json");
    // Home TCP is (0.3069, 0, 0.4869) pointing down; move 10 cm, then an unreachable pose.
    std::fs::write(
        &keyframes,
        r#"{"keyframes":[
            {"position":[0.40,0.05,0.45],"quat_wxyz":[0.0,1.0,0.0,0.0],"gripper_open":true},
            {"position":[2.0,0.0,0.5],"quat_wxyz":[0.0,1.0,0.0,0.0],"gripper_open":true}]}"#,
    )
    .unwrap();
    let log = dir.path().join("run.csv");
    let out = common::flowram()
        .args(["track", "--json", "--keyframes"])
        .arg(&keyframes)
        .arg("--log")
        .arg(&log)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let k = report["keyframes"].as_array().unwrap();
    assert_eq!(k.len(), 2);
    assert_eq!(k[0]["reached"], true);
    assert!(k[0]["pos_err_mm"].as_f64().unwrap() <= 1.0 && k[0]["rot_err_deg"].as_f64().unwrap() <= 0.5);
    assert!(k[0]["time_s"].as_f64().unwrap() > 0.1);
    assert!(k[0]["error"].is_null());
    assert_eq!(k[1]["reached"], false);
    assert!(k[1]["error"].as_str().unwrap().contains("reaches at most"));
    assert_eq!(report["limit_violations"], 0);
    assert!(report["max_torque_ratio"].as_f64().unwrap() <= 1.0);
    assert!(report["max_torque_rate_ratio"].as_f64().unwrap() <= 1.0 + 1e-9);

    let csv = std::fs::read_to_string(&log).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(header.len(), 1 + 7 * 3 + 7 + 7 + 7);
    assert_eq!(&header[..2], &["t", "q1"]);
    let rows: Vec<Vec<f64>> = lines.map(|l| l.split(',').map(|v| v.parse().unwrap()).collect()).collect();
    assert!(rows.len() > 100 && rows.iter().all(|r| r.len() == header.len()));
    assert!(rows.windows(2).all(|w| w[1][0] > w[0][0]), "time increases");
}

#[test]
fn bad_keyframe_files_get_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let run = |content: Option<&str>| {
        let path = dir.path().join("k.json");
        match content {
            Some(c) => std::fs::write(&path, c).unwrap(),
            None => {
                let _ = std::fs::remove_file(&path);
            }
        }
        let out = common::flowram().args(["track", "--keyframes"]).arg(&path).output().unwrap();
        assert_eq!(out.status.code(), Some(1));
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(!err.contains("panicked"), "{err}");
        err
    };
    assert!(run(None).contains("cannot read the keyframes file"));
    let err = run(Some("{\"keyframes\": [ {\"position\": [0.4, 0.0]} ]}"));
    assert!(err.contains("quat_wxyz") && err.contains("expected"), "{err}");
    let err = run(Some(
        "{\"keyframes\": [{\"position\":[0.4,0,0.4],\"quat_wxyz\":[0,1,0,0],\"gripper_open\":true,\"speed\":2}]}",
    ));
    assert!(err.contains("speed"), "{err}");
    assert!(run(Some("{\"keyframes\": []}")).contains("no keyframes"));
    let out = common::flowram().args(["tune", "--step", "0.1,0"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "clap usage error");
    assert!(String::from_utf8_lossy(&out.stderr).contains("dx,dy,dz"));
}

#[test]
fn tune_measures_a_step_and_plots_it() {
    let dir = tempfile::tempdir().unwrap();
    let plot = dir.path().join("step.png");
    let out = common::flowram()
        .args(["tune", "--step", "0.05,0,0", "--duration", "1.0", "--json", "--plot"])
        .arg(&plot)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in ["rise_time_s", "overshoot_pct", "settling_time_s", "steady_state_error_mm", "peak_torque_ratio"] {
        assert!(r[key].as_f64().is_some(), "{key} in {r}");
    }
    let (info, _) = decode_png(&plot);
    assert_eq!((info.width, info.height), (1200, 800));
}

#[test]
fn run_and_collect_write_what_they_report() {
    let dir = tempfile::tempdir().unwrap();
    let gif = dir.path().join("episode.gif");
    let out = common::flowram()
        .args(["run", "--task", "push_buttons", "--seed", "1", "--json", "--video"])
        .arg(&gif)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["task"], "push_buttons");
    assert_eq!(r["success"], true);
    assert!(r["instruction"].as_str().unwrap().starts_with("push the "));
    assert!(r["keyframes"].as_u64().unwrap() >= 3);
    let bytes = std::fs::read(&gif).unwrap();
    assert!(bytes.starts_with(b"GIF89a") && bytes.len() > 10_000, "an animated GIF");

    let data = dir.path().join("data");
    let out = common::flowram()
        .args([
            "collect",
            "--task",
            "push_buttons",
            "--episodes",
            "2",
            "--seed",
            "5",
            "--cameras",
            "front,wrist",
            "--size",
            "64",
            "--json",
            "--out",
        ])
        .arg(&data)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let c: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!((c["episodes"].as_u64(), c["successes"].as_u64()), (Some(2), Some(2)));
    assert!(c["keyframes_mean"].as_f64().unwrap() >= 3.0 && c["seconds"].as_f64().unwrap() > 0.0);
    let loaded = flowram::data::load_dataset(&data).unwrap();
    assert_eq!(loaded.episodes.len(), 2);
    assert!(loaded.failures.is_empty());
    assert!(loaded.episodes.iter().all(|e| e.success && e.cameras == ["front", "wrist"] && e.height == 64));

    // recovery samples: recorded in the manifest, and the same folder refuses another request
    let perturbed = dir.path().join("perturbed");
    let collect = |extra: &[&str]| {
        common::flowram()
            .args(["collect", "--task", "slide_block", "--episodes", "1", "--cameras", "front", "--size", "32"])
            .args(extra)
            .arg("--out")
            .arg(&perturbed)
            .output()
            .unwrap()
    };
    let out = collect(&["--perturb-sigma", "0.03", "--perturb-probability", "1"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(perturbed.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(
        manifest["perturbation"],
        serde_json::json!({"probability": 1.0, "sigma_m": 0.03, "target": "next", "grasp_probability": 0.0, "detours": 1})
    );
    let loaded = flowram::data::load_dataset(&perturbed).unwrap();
    assert_eq!(loaded.episodes[0].proprio.len() / 8, 5, "slide_block's 4 keyframes and one detour");
    let out = collect(&["--perturb-sigma", "0.03", "--perturb-probability", "1", "--perturb-target", "approach"]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--perturb-target next") && !err.contains("panicked"), "{err}");
    let out = collect(&["--perturb-sigma", "0.5"]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("at most 0.1 m") && !err.contains("panicked"), "{err}");
    let out = collect(&["--perturb-sigma", "0.03", "--perturb-grasp-probability", "2"]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("missed-grasp probability is 2") && !err.contains("panicked"), "{err}");

    let out = common::flowram().args(["run", "--task", "juggle"]).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("push_buttons"));
    let out = common::flowram().args(["run", "--task", "open_drawer", "--variation", "7"]).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("out of range"), "{}", String::from_utf8_lossy(&out.stderr));
    let out = common::flowram()
        .args(["collect", "--task", "push_buttons", "--episodes", "1", "--cameras", "top", "--out"])
        .arg(dir.path().join("none"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("front, left_shoulder, right_shoulder, wrist") && !err.contains("panicked"), "{err}");
    assert!(!dir.path().join("none").exists(), "nothing is written before the inputs are checked");
}

#[test]
fn runtime_benchmarks_print_their_figures_and_refuse_bad_arguments() {
    let out = common::flowram().args(["bench", "realtime", "--ticks", "1500", "--no-rt", "--json"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rt: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(rt["ticks"], 1500);
    assert_eq!(rt["waited_on_policy_ticks"], 0);
    assert_eq!(rt["allocations_in_tick"], 0, "the binary counts allocations in ticks: {rt}");
    assert_eq!(rt["rt_scheduling"], false);
    for key in ["compute_us", "wake_latency_us"] {
        for p in ["p50", "p99", "p9999", "max"] {
            assert!(rt[key][p].as_f64().is_some_and(|v| v > 0.0), "{key}.{p} in {rt}");
        }
    }
    assert!(rt["deadline_misses"].as_u64().is_some() && rt["policy_inferences"] == 0);
    let causes = &rt["deadline_miss_causes"];
    let by_cause: u64 = ["overrun", "wake", "backend", "compute"].iter().map(|k| causes[k].as_u64().unwrap()).sum();
    assert_eq!(Some(by_cause), rt["deadline_misses"].as_u64(), "every miss has one cause: {rt}");
    assert!(rt["host_steal_s"].as_f64().is_some_and(|s| s >= 0.0), "/proc/stat is readable here: {rt}");
    assert!(rt["one_core"].is_null(), "{rt}");
    let out = common::flowram()
        .args(["bench", "realtime", "--ticks", "1500", "--no-rt", "--one-core", "--json"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rt: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    // the child inherits this process's cores, so its control core is the one computed here
    let core = flowram::runtime::pacing::control_core() as u64;
    assert_eq!(rt["one_core"], core, "the process runs on the control thread's core: {rt}");
    assert_eq!((rt["ticks"].as_u64(), rt["allocations_in_tick"].as_u64()), (Some(1500), Some(0)), "{rt}");

    let out = common::flowram().args(["bench", "faults", "--runs", "2", "--json"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let faults: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(faults["runs"], 2);
    assert_eq!(faults["panics"], 0);
    assert_eq!(faults["non_finite_torques"], 0);

    for (args, expected) in [
        (&["bench", "realtime", "--ticks", "0"][..], "--ticks"),
        (&["bench", "faults", "--runs", "0"][..], "--runs"),
        (&["run", "--task", "open_drawer", "--realtime", "--video", "x.gif"][..], "--video"),
        (&["run", "--task", "open_drawer", "--latency-ms", "100"][..], "--realtime"),
        (&["run", "--task", "stack_blocks", "--policy", "flowram", "--consensus", "mean"][..], "`medoid` or `mode`"),
        (&["bench", "success", "--tasks", "stack_blocks", "--pointer-temperature", "0"][..], "above 0"),
        (&["bench", "success", "--tasks", "stack_blocks", "--pointer-guidance=-1"][..], "at least 0"),
        (&["predict", "--checkpoint", "x", "--episode", "y", "--keyframe", "0", "--consensus", "mean"][..], "`medoid`"),
        (
            &["bench", "heldout", "--checkpoint", "x", "--data", "y", "--train-data", "z", "--pointer-temperature=-1"]
                [..],
            "above 0",
        ),
    ] {
        let out = common::flowram().args(args).output().unwrap();
        assert!(!out.status.success(), "{args:?} succeeded");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(expected), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
}

#[test]
fn predict_prints_every_sample_and_marks_the_executed_one() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("held");
    let out = common::flowram()
        .args(["collect", "--task", "open_drawer", "--episodes", "1", "--seed", "1000", "--cameras", "front,wrist"])
        .arg("--out")
        .arg(&data)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let checkpoint = flowram::deps::models_dir().join("policy/pretrained/five-tasks");
    let predict = |extra: &[&str]| {
        let out = common::flowram()
            .arg("predict")
            .arg("--checkpoint")
            .arg(&checkpoint)
            .arg("--episode")
            .arg(data.join("episode_00000.safetensors"))
            .args(["--keyframe", "0", "--samples", "5", "--json"])
            .args(extra)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
    };
    let position = |p: &serde_json::Value| -> Vec<f64> {
        p["keyframe"]["position"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect()
    };
    let report = predict(&[]);
    assert_eq!((report["consensus"].as_str(), report["pointer_temperature"].as_f64()), (Some("medoid"), Some(1.0)));
    let positions: Vec<Vec<f64>> = report["predictions"].as_array().unwrap().iter().map(position).collect();
    assert_eq!(positions.len(), 5);
    // the medoid: the least summed distance to the other samples
    let summed = |a: &Vec<f64>| -> f64 {
        positions.iter().map(|b| a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>().sqrt()).sum()
    };
    let medoid = (0..5).min_by(|&i, &j| summed(&positions[i]).total_cmp(&summed(&positions[j]))).unwrap();
    assert_eq!(report["executed"].as_u64(), Some(medoid as u64), "{positions:?}");
    let sharpened = predict(&["--consensus", "mode", "--pointer-temperature", "0.25"]);
    assert_eq!(sharpened["consensus"], "mode");
    assert_eq!(sharpened["pointer_temperature"].as_f64(), Some(0.25));
    assert!(sharpened["executed"].as_u64().unwrap() < 5);
}

/// A results file of `bench success --out` on two tasks, seeds 1000-1003, with these successes.
fn results_file(path: &std::path::Path, digest: &str, successes: [[bool; 4]; 2], seed: u64) {
    let mut outcomes = Vec::new();
    // recorded out of order, as shards merged or resumed runs may leave them
    for i in (0..4).rev() {
        for (task, row) in successes.iter().enumerate() {
            outcomes.push(serde_json::json!({
                "task": task, "seed": seed + i as u64, "variation": i, "success": row[i],
                "keyframes": 4, "reached": 4, "inference_ms": 20.0
            }));
        }
    }
    let record = serde_json::json!({
        "format": "flowram-success-v1", "revision": "test", "checkpoint": "a", "checkpoint_digest": digest,
        "tasks": ["open_drawer", "push_buttons"], "episodes": 4, "seed": seed, "max_keyframes": 25, "steps": 8,
        "samples": 1, "drs": true, "cameras": ["front"], "shard": {"index": 0, "count": 1}, "outcomes": outcomes
    });
    std::fs::write(path, serde_json::to_vec(&record).unwrap()).unwrap();
}

#[test]
fn bench_compare_pairs_two_results_files_on_their_seeds() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b, other) = (dir.path().join("a.json"), dir.path().join("b.json"), dir.path().join("c.json"));
    results_file(&a, "aa", [[true, true, true, false], [true, false, false, false]], 1000);
    results_file(&b, "bb", [[false, true, false, true], [true, false, false, false]], 1000);
    results_file(&other, "cc", [[true; 4], [true; 4]], 2000);
    let out = common::flowram().args(["bench", "compare", "--json"]).arg(&a).arg(&b).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let rows = report["comparison"].as_array().unwrap();
    let row = |task: &str| rows.iter().find(|r| r["task"] == task).unwrap();
    // open_drawer: seeds 1000 and 1002 only by a, 1003 only by b; push_buttons: the same
    assert_eq!(
        (row("open_drawer")["only_checkpoint"].as_u64(), row("open_drawer")["only_baseline"].as_u64()),
        (Some(2), Some(1))
    );
    assert_eq!(
        (row("push_buttons")["only_checkpoint"].as_u64(), row("push_buttons")["only_baseline"].as_u64()),
        (Some(0), Some(0))
    );
    assert_eq!((row("all")["only_checkpoint"].as_u64(), row("all")["only_baseline"].as_u64()), (Some(2), Some(1)));
    assert_eq!(report["checkpoint"][0]["successes"].as_u64(), Some(3));
    assert_eq!(report["baseline"][0]["successes"].as_u64(), Some(2));

    // other seeds: refused, naming both files
    let out = common::flowram().args(["bench", "compare"]).arg(&a).arg(&other).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("a.json") && err.contains("c.json") && err.contains("same episodes"), "{err}");
    // other expert versions are other scenes: refused; a record without versions is paired, with a warning
    let (v1, v2) = (dir.path().join("v1.json"), dir.path().join("v2.json"));
    for (path, versions) in [(&v1, [1, 1]), (&v2, [1, 2])] {
        results_file(path, "vv", [[true; 4], [true; 4]], 1000);
        let mut record: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
        record["expert_versions"] = serde_json::json!(versions);
        std::fs::write(path, serde_json::to_vec(&record).unwrap()).unwrap();
    }
    let out = common::flowram().args(["bench", "compare"]).arg(&v2).arg(&v1).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("same scenes") && err.contains("push_buttons 2") && err.contains("push_buttons 1"), "{err}");
    let out = common::flowram().args(["bench", "compare"]).arg(&v2).arg(&a).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && err.contains("a.json predates recorded expert versions"), "{err}");
    // a missing file says how to make one
    let out = common::flowram().args(["bench", "compare"]).arg(&a).arg(dir.path().join("none.json")).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.code() == Some(1) && err.contains("none.json") && err.contains("bench success --out"), "{err}");
}

#[test]
fn bench_grid_tabulates_and_plots_recorded_evaluations() {
    // Two real evaluations the project records (docs/results): the shipped checkpoint and arm J2.
    let (shipped, j2) = ("docs/results/five-tasks-c8-guards.json", "docs/results/five-tasks-j2.json");
    let dir = tempfile::tempdir().unwrap();
    let plot = dir.path().join("grid.png");
    let out = common::flowram().args(["bench", "grid", "--json", j2, shipped, "--plot"]).arg(&plot).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let cells: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let summary: Vec<(&str, u64, u64, u64)> = cells
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let n = |k: &str| c[k].as_u64().unwrap();
            (c["arm"].as_str().unwrap(), n("steps"), n("successes"), n("episodes"))
        })
        .collect();
    assert_eq!(summary, [("five-tasks", 8, 107, 250), ("five-tasks-fw", 8, 115, 250)]);
    let (info, pixels) = decode_png(&plot);
    assert_eq!((info.width, info.height), (1200, 450));
    let coloured = pixels.chunks(info.color_type.samples()).filter(|p| (p[0] as i32 - p[2] as i32).abs() > 60).count();
    assert!(coloured > 100, "the arms are drawn: {coloured} coloured pixels");

    // The same cell twice, and a missing file: refused, saying why.
    let out = common::flowram().args(["bench", "grid", j2, j2]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.code() == Some(1) && err.contains("same cell"), "{err}");
    let out = common::flowram().args(["bench", "grid", j2, "none.json"]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.code() == Some(1) && err.contains("none.json") && err.contains("bench success --out"), "{err}");
}
