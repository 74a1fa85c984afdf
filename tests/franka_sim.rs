//! The Franka backend against a real peer: `flowram track --backend franka` drives franka-sim
//! (PyPI franka-sim 1.1.7, a MuJoCo server speaking the Franka network protocol as an FR3;
//! installed by scripts/setup.sh into .deps/franka-sim) over 127.0.0.1, with the server's
//! communication-constraint and motion-limit enforcement on. The server runs our installed
//! Panda MJCF with rotor inertia added (FR3_MJCF; see `server_arm_mjcf`), so nothing is
//! downloaded.
//!
//! Needs `--features franka` (`.ci/run` runs it).
#![cfg(feature = "franka")]

mod common;

use std::io::Read;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use flowram::deps::Deps;
use flowram::robot::{JointVector, Kinematics};

/// The server's initial arm configuration (franka_sim/mujoco_franka_sim.py, ARM_INITIAL_Q).
const SERVER_START_Q: [f64; 7] = [0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785];

/// The arm model the server simulates: our installed Panda MJCF with the motors' reflected
/// rotor inertia (`armature`, 0.1 kg m^2 per joint, MuJoCo Menagerie's Panda and FR3 value),
/// written to `dir` with absolute mesh paths. The dm-robotics-panda model has none, and
/// franka-sim's idle hold (an explicit PD, 4500 / 450 on joint 1) is then unstable on the
/// light mode where joints 1 and 3 turn against each other (their axes align at the start
/// pose): the arm shook at up to 2.3 rad/s between sessions, and a session could start into a
/// joint_velocity_violation reflex.
fn server_arm_mjcf(deps: &Deps, dir: &Path) -> PathBuf {
    let arm = deps.panda_arm_mjcf().unwrap();
    let folder = arm.parent().unwrap().display().to_string();
    assert!(!folder.contains(['"', '&', '<']), "{folder}: the MJCF attribute below would need escaping");
    let xml = std::fs::read_to_string(&arm).unwrap();
    let compiler = r#"<compiler angle="radian" />"#;
    assert!(xml.contains(compiler), "{} changed: no `{compiler}`", arm.display());
    let joints = xml.matches(r#"<joint name="panda_joint"#).count();
    assert_eq!(joints, 7, "{}: expected 7 arm joints", arm.display());
    let xml = xml
        .replace(compiler, &format!(r#"<compiler angle="radian" meshdir="{folder}" texturedir="{folder}" />"#))
        .replace(r#"<joint name="panda_joint"#, r#"<joint armature="0.1" name="panda_joint"#);
    let path = dir.join("panda_rotor_inertia.xml");
    std::fs::write(&path, xml).unwrap();
    path
}

/// franka-sim on a free port; SIGINT (its clean shutdown) and then SIGKILL when dropped.
struct Server {
    child: Child,
    log: PathBuf,
    port: u16,
}

impl Server {
    fn start(dir: &Path) -> Server {
        let deps = Deps::locate();
        let exe = deps.root().join("franka-sim/bin/run-franka-sim-server");
        assert!(exe.is_file(), "{} is missing: run scripts/setup.sh", exe.display());
        let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let log = dir.join("server.log");
        let child = Command::new(exe)
            .args(["--port", &port.to_string(), "--enforce-comm-constraints", "--enforce-motion-limits"])
            .env("FR3_MJCF", server_arm_mjcf(&deps, dir))
            .env("FRANKA_HAND_MJCF", deps.panda_hand_mjcf().unwrap())
            .env("PYTHONUNBUFFERED", "1")
            .stdout(std::fs::File::create(&log).unwrap())
            .stderr(Stdio::from(std::fs::File::options().append(true).open(&log).unwrap()))
            .spawn()
            .expect("start franka-sim");
        let server = Server { child, log, port };
        let deadline = Instant::now() + Duration::from_secs(90);
        while !server.log().contains("Server ready for new client connection") {
            assert!(Instant::now() < deadline, "franka-sim did not come up in 90 s:\n{}", server.log());
            std::thread::sleep(Duration::from_millis(200));
        }
        server
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        // SAFETY: signalling our own child process.
        unsafe { libc::kill(self.child.id() as i32, libc::SIGINT) };
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Runs `cmd` with a time-out, calling `meanwhile` with its pid once started; (exit success,
/// stdout, stderr).
fn run_with_timeout(mut cmd: Command, timeout: Duration, meanwhile: impl FnOnce(u32)) -> (bool, String, String) {
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    meanwhile(child.id());
    let (mut out, mut err) = (child.stdout.take().unwrap(), child.stderr.take().unwrap());
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        out.read_to_string(&mut s).unwrap();
        s
    });
    let err_reader = std::thread::spawn(move || {
        let mut s = String::new();
        err.read_to_string(&mut s).unwrap();
        s
    });
    let deadline = Instant::now() + timeout;
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("flowram track did not finish in {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    (status.success(), reader.join().unwrap(), err_reader.join().unwrap())
}

/// Keyframes around the server's start pose (robot base frame): 8 cm forward and down with the
/// fingers closing, 10 cm sideways, then back up opening them; written to `dir`.
fn keyframes_file(dir: &Path) -> PathBuf {
    let world = flowram::sim::World::load_named("default").unwrap();
    let mut kinematics = Kinematics::new(&world.arm_description().unwrap()).unwrap();
    let start = kinematics.tcp(&JointVector::from_column_slice(&SERVER_START_Q)).unwrap();
    let quat = start.rotation.quaternion();
    let p = start.translation.vector;
    let keyframe = |dx: f64, dy: f64, dz: f64, open: bool| serde_json::json!({"position": [p.x + dx, p.y + dy, p.z + dz], "quat_wxyz": [quat.w, quat.i, quat.j, quat.k], "gripper_open": open});
    let keyframes = serde_json::json!({"keyframes": [
        keyframe(0.08, 0.0, -0.08, false),
        keyframe(0.08, 0.10, -0.08, false),
        keyframe(0.0, 0.0, 0.0, true),
    ]});
    let file = dir.join("keyframes.json");
    std::fs::write(&file, keyframes.to_string()).unwrap();
    file
}

fn track(server: &Server, keyframes: &Path) -> Command {
    let mut track = common::flowram();
    track.args(["track", "--backend", "franka", "--robot", "fr3", "--json", "--keyframes"]).arg(keyframes);
    track.args(["--robot-ip", &format!("127.0.0.1:{}", server.port)]);
    track
}

/// One server for both scenarios (its hand service always takes port 1338, so two servers
/// cannot run at once): a clean run, then a run that stops answering.
#[test]
fn track_on_franka_sim() {
    let dir = tempfile::tempdir().unwrap();
    let file = keyframes_file(dir.path());
    let server = Server::start(dir.path());
    clean_run_reaches_keyframes_within_the_robots_limits(&server, &file);
    a_stalled_client_is_aborted_recovered_and_the_robot_runs_again(&server, &file);
}

fn clean_run_reaches_keyframes_within_the_robots_limits(server: &Server, file: &Path) {
    let track = track(server, file);
    let (ok, stdout, stderr) = run_with_timeout(track, Duration::from_secs(120), |_| {});
    let server_log = server.log();
    assert!(ok, "track failed:\n{stderr}\nserver:\n{server_log}");
    let report: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    eprintln!("{report:#}");

    for (i, k) in report["keyframes"].as_array().unwrap().iter().enumerate() {
        assert!(k["reached"].as_bool().unwrap(), "keyframe {i} not reached: {k}");
        assert!(k["pos_err_mm"].as_f64().unwrap() < 2.0, "keyframe {i}: {k}");
    }
    assert_eq!(report["limit_violations"], 0, "{report}");
    // motions are planned at half the joint velocity limits (controllers/osc.toml); more means
    // the arm was moving before we commanded it (it shook at 89 % without rotor inertia)
    let velocity = report["max_velocity_ratio"].as_f64().unwrap();
    assert!(velocity < 0.6, "a joint reached {velocity} of its velocity limit");
    let franka = &report["franka"];
    // the torque rate on the server's side: consecutive torques it received (its echo is
    // float32: 1e-4 Nm of rounding at these torques)
    let step = franka["max_received_torque_step"].as_f64().unwrap();
    assert!(step <= 1.0 + 1e-4, "the robot received a torque step of {step} Nm in 1 ms");
    assert!(franka["cycles"].as_u64().unwrap() > 1000, "{franka}");
    // the controller keeps to the limits itself: the guard only trims rounding-sized excess,
    // unless the robot lost commands (a loaded machine slows the Python server: its success rate
    // then drops below 1 and the guard measures the rate from the torque the robot last got,
    // which is its job, and the received step above stays within the limit)
    let trimmed = franka["max_guard_change"].as_f64().unwrap();
    let lost = franka["min_command_success_rate"].as_f64().unwrap() < 1.0;
    assert!(trimmed < 1e-3 || lost, "the torque guard changed a command by {trimmed} Nm with no command lost");
    // and even then by no more than a few lost cycles' worth of the 1 Nm/ms rate limit
    assert!(trimmed < 10.0, "the torque guard changed a command by {trimmed} Nm");
    // the hand was told to close and to open again (it starts open: nothing to send first)
    assert_eq!(franka["gripper_commands"].as_u64(), Some(2), "{franka}");
    assert_eq!(franka["gripper_failures"].as_u64(), Some(0), "{franka}");
    // no abort (the run would have failed) and nothing the server flagged
    for bad in ["communication_constraints_violation", "Reflex", "limits_violation", "discontinuity"] {
        assert!(!server_log.contains(bad), "the server logged `{bad}`:\n{server_log}");
    }
}

/// The client stops answering for 200 ms mid-motion (SIGSTOP): the server aborts the motion
/// with communication_constraints_violation after 20 lost cycles; track reports it as a
/// communication failure, runs automatic error recovery, and a new run then succeeds.
fn a_stalled_client_is_aborted_recovered_and_the_robot_runs_again(server: &Server, file: &Path) {
    let sessions = |log: &str| log.matches("Setting control mode to TORQUE").count();
    let before = sessions(&server.log());
    let (ok, _, stderr) = run_with_timeout(track(server, file), Duration::from_secs(120), |pid| {
        // mid-run: 1 s after the torque session started (a run is about 3.3 s of robot time)
        let deadline = Instant::now() + Duration::from_secs(60);
        while sessions(&server.log()) == before {
            assert!(Instant::now() < deadline, "the client never started a torque session");
            std::thread::sleep(Duration::from_millis(20));
        }
        std::thread::sleep(Duration::from_millis(1000));
        // SAFETY: signalling our own child process.
        unsafe { libc::kill(pid as i32, libc::SIGSTOP) };
        std::thread::sleep(Duration::from_millis(200));
        unsafe { libc::kill(pid as i32, libc::SIGCONT) };
    });
    assert!(!ok, "a client stalled for 200 ms was not stopped:\n{stderr}\nserver:\n{}", server.log());
    assert!(stderr.contains("communication with the robot failed"), "{stderr}");
    assert!(stderr.contains("recovered (automatic error recovery)"), "{stderr}");
    let (ok, stdout, stderr) = run_with_timeout(track(server, file), Duration::from_secs(120), |_| {});
    assert!(ok, "the run after recovery failed:\n{stderr}\nserver:\n{}", server.log());
    let report: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert!(report["keyframes"].as_array().unwrap().iter().all(|k| k["reached"] == true), "{report}");
}
