//! Controller configs are validated: a negative gain, a missing field, a wrong unit or an
//! unknown key gives an error naming the field; units are converted.
use std::path::Path;

use flowram::control::osc_config::OscConfig;
use flowram::deps::controllers_dir;
use flowram::robot::JointLimits;
use flowram::unit_config::ConfigFile;

fn osc_text() -> String {
    std::fs::read_to_string(controllers_dir().join("osc.toml")).unwrap()
}

fn osc_error(text: &str) -> String {
    OscConfig::from_config(ConfigFile::parse(Path::new("osc.toml"), text).unwrap()).unwrap_err().to_string()
}

#[test]
fn shipped_profiles_load() {
    let c = OscConfig::default_profile().unwrap();
    assert_eq!(c.position.stiffness.x, 900.0);
    assert!((c.reached_orientation - 0.5f64.to_radians()).abs() < 1e-12, "deg converted to rad");
    assert!((c.reached_position - 0.001).abs() < 1e-12, "mm converted to m");
    assert_eq!(c.time_limit, 0.0, "no wall-clock limit in the shipped (simulation) profile");
    assert_eq!(c.scaling_iterations, 4);
    let real_time = osc_text()
        .replace("time_limit = { value = 0.0, unit = \"us\" }", "time_limit = { value = 500.0, unit = \"us\" }");
    let c = OscConfig::from_config(ConfigFile::parse(Path::new("osc.toml"), &real_time).unwrap()).unwrap();
    assert!((c.time_limit - 500e-6).abs() < 1e-12, "us converted to s");
    let l = JointLimits::panda().unwrap();
    assert_eq!(l.torque[0], 87.0);
    assert_eq!(l.torque_rate[6], 1000.0);
    assert!(c.external_torque_in_limits && c.reflex_enabled, "the contact guards are on by default");
}

#[test]
fn the_unguarded_profile_is_the_default_with_the_contact_guards_off() {
    let unguarded = std::fs::read_to_string(controllers_dir().join("osc-unguarded.toml")).unwrap();
    let u = OscConfig::from_config(ConfigFile::parse(Path::new("osc-unguarded.toml"), &unguarded).unwrap()).unwrap();
    assert!(!u.external_torque_in_limits && !u.reflex_enabled);
    // Line for line the default's, but for its header comment and the two switches.
    let body = |text: &str| -> Vec<String> {
        text.lines()
            .skip_while(|l| l.starts_with('#'))
            .map(|l| l.replace("external_torque_in_limits = false", "external_torque_in_limits = true"))
            .map(|l| if l == "enabled = false" { "enabled = true".to_string() } else { l })
            .collect()
    };
    assert_eq!(body(&unguarded), body(&osc_text()), "osc-unguarded.toml drifted from osc.toml");
}

#[test]
fn negative_gain_names_the_field() {
    let text = osc_text().replacen(
        "stiffness = { values = [900.0, 900.0, 900.0], unit = \"1/s^2\" }",
        "stiffness = { values = [900.0, -900.0, 900.0], unit = \"1/s^2\" }",
        1,
    );
    let err = osc_error(&text);
    assert!(err.contains("task.position.stiffness") && err.contains("negative"), "{err}");
}

#[test]
fn missing_field_names_the_field() {
    let text = osc_text().replacen("damping_ratio = 1.0\n", "", 1);
    let err = osc_error(&text);
    assert!(err.contains("nullspace.damping_ratio") && err.contains("missing"), "{err}");
}

#[test]
fn wrong_unit_names_the_field_and_the_expected_units() {
    let text = osc_text().replacen("unit = \"1/s^2\"", "unit = \"N/m\"", 1);
    let err = osc_error(&text);
    assert!(
        err.contains("task.position.stiffness") && err.contains("wrong unit \"N/m\"") && err.contains("1/s^2"),
        "{err}"
    );
    let text =
        osc_text().replace("position = { value = 1.0, unit = \"mm\" }", "position = { value = 1.0, unit = \"deg\" }");
    let err = osc_error(&text);
    assert!(err.contains("reached.position") && err.contains("\"m\""), "{err}");
    let text = osc_text().replace("position = { value = 1.0, unit = \"mm\" }", "position = 1.0");
    let err = osc_error(&text);
    assert!(err.contains("reached.position") && err.contains("unit"), "{err}");
}

#[test]
fn unknown_keys_and_bad_values_are_refused() {
    let err = osc_error(&osc_text().replace("posture_weight", "posture_wieght"));
    assert!(err.contains("qp.posture_weight") || err.contains("qp.posture_wieght"), "{err}");
    let err = osc_error(&osc_text().replace("velocity_scale = 0.5", "velocity_scale = 1.5"));
    assert!(err.contains("motion.velocity_scale") && err.contains("(0, 1]"), "{err}");
    for bad in ["2.5", "-1", "1000"] {
        let err = osc_error(&osc_text().replace("scaling_iterations = 4", &format!("scaling_iterations = {bad}")));
        assert!(err.contains("qp.scaling_iterations"), "{bad}: {err}");
    }
    let c = OscConfig::from_config(
        ConfigFile::parse(
            Path::new("osc.toml"),
            &osc_text().replace("scaling_iterations = 4", "scaling_iterations = 0"),
        )
        .unwrap(),
    )
    .unwrap();
    assert_eq!(c.scaling_iterations, 0, "0 turns OSQP's scaling off");
    let err = ConfigFile::parse(Path::new("osc.toml"), "this is [not toml").err().unwrap().to_string();
    assert!(err.contains("not valid TOML"), "{err}");
}

#[test]
fn limits_file_is_validated_and_converted() {
    let path = controllers_dir().join("panda_limits.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let parse = |t: &str| JointLimits::from_config(ConfigFile::parse(&path, t).unwrap());
    let err = parse(&text.replace("velocity = { values = [2.1750", "velocity = { values = [-2.1750"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("joint.velocity") && err.contains("> 0"), "{err}");
    let err = parse(&text.replace("unit = \"Nm/s\"", "unit = \"Nm\"")).unwrap_err().to_string();
    assert!(err.contains("joint.torque_rate") && err.contains("wrong unit"), "{err}");
    let err = parse(&text.replace("jerk = {", "jerky = {")).unwrap_err().to_string();
    assert!(err.contains("joint.jerk") && err.contains("missing"), "{err}");
    let in_degrees = text.replace(
        "velocity = { values = [2.1750, 2.1750, 2.1750, 2.1750, 2.6100, 2.6100, 2.6100], unit = \"rad/s\" }",
        "velocity = { values = [180, 180, 180, 180, 180, 180, 180], unit = \"deg/s\" }",
    );
    let l = parse(&in_degrees).unwrap();
    assert!((l.velocity[0] - std::f64::consts::PI).abs() < 1e-12);
}
