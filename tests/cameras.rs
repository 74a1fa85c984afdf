//! Cameras and point clouds, checked against geometry: a box of known size and pose, the table
//! plane, and agreement between cameras; plus deterministic rendering.
mod common;

use flowram::sim::scene::CAMERAS;
use flowram::sim::{CameraRig, PointCloud, RgbdFrame, Visuals, World};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

const HALF: [f64; 3] = [0.04, 0.03, 0.05];
const TABLE_Z: f64 = 0.75;

fn box_pose() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.45, 0.12, TABLE_Z + HALF[2]),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 30f64.to_radians()),
    )
}

/// Scene with a free box (placed by set_body_pose, so that path is exercised too).
fn box_world() -> (common::TempScene, World) {
    let scene = common::scene_with(&format!(
        r#"<body name="probe_box" pos="0.3 -0.3 1.2"><freejoint/><geom type="box" size="{} {} {}" rgba="0.9 0.2 0.2 1"/></body>"#,
        HALF[0], HALF[1], HALF[2]
    ));
    let mut world = common::load(&scene);
    world.set_body_pose("probe_box", &box_pose()).unwrap();
    (scene, world)
}

/// Distance from a point (box frame) to the box surface.
fn distance_to_box_surface(p: &Vector3<f64>) -> f64 {
    let q: Vector3<f64> = Vector3::from_fn(|i, _| p[i].abs() - HALF[i]);
    let outside = q.map(|v| v.max(0.0)).norm();
    let inside = q.max().min(0.0);
    (outside + inside).abs()
}

fn render_all(world: &mut World, rig: &mut CameraRig) -> Vec<RgbdFrame> {
    CAMERAS.iter().map(|c| rig.render(world, rig.camera_index(c).unwrap()).unwrap()).collect()
}

#[test]
fn box_points_lie_on_its_faces_in_every_camera() {
    let (_scene, mut world) = box_world();
    let mut rig = CameraRig::new(&world, 128, Visuals::Full).unwrap();
    let to_box = box_pose().inverse();
    for frame in render_all(&mut world, &mut rig) {
        let cloud = PointCloud::from_frame(&frame, None);
        let mut on_box = 0;
        let mut worst: f64 = 0.0;
        for p in &cloud.points {
            let p = p.cast::<f64>();
            let local = to_box * p;
            let near_box = (0..3).all(|i| local[i].abs() <= HALF[i] + 0.01);
            if near_box && p.z > TABLE_Z + 0.002 {
                on_box += 1;
                worst = worst.max(distance_to_box_surface(&local.coords));
            }
        }
        assert!(on_box >= 20, "camera {}: only {on_box} points on the box", frame.camera);
        assert!(worst <= 0.003, "camera {}: a box point lies {:.2} mm off the box surface", frame.camera, worst * 1e3);
    }
}

#[test]
fn table_points_lie_on_the_table_plane() {
    let (_scene, mut world) = box_world();
    let mut rig = CameraRig::new(&world, 128, Visuals::Full).unwrap();
    let box_centre = box_pose().translation.vector;
    for frame in render_all(&mut world, &mut rig) {
        let cloud = PointCloud::from_frame(&frame, None);
        let mut n = 0;
        for p in &cloud.points {
            let p = p.cast::<f64>();
            // Table top (x in [-0.3, 0.9], |y| < 0.7) with a 2 cm margin, away from the robot's
            // footprint and the box: only the table can be seen there.
            let on_top = p.x > -0.28 && p.x < 0.88 && p.y.abs() < 0.68;
            let robot = p.x < 0.5 && p.y.abs() < 0.2;
            let near_box = (p.coords.xy() - box_centre.xy()).norm() < 0.12;
            if on_top && !robot && !near_box && p.z < 1.0 {
                n += 1;
                assert!((p.z - TABLE_Z).abs() < 0.003, "camera {}: table point at z = {:.4}", frame.camera, p.z);
            }
        }
        if frame.camera != "wrist" {
            assert!(n > 500, "camera {} sees only {n} table points", frame.camera);
        }
    }
}

/// Bilinear depth at a sub-pixel position, if the 4 neighbours lie on one smooth surface.
fn depth_at(frame: &RgbdFrame, u: f64, v: f64) -> Option<f64> {
    let k = &frame.intrinsics;
    let (u0, v0) = (u.floor(), v.floor());
    if u0 < 0.0 || v0 < 0.0 || u0 + 1.0 >= k.width as f64 || v0 + 1.0 >= k.height as f64 {
        return None;
    }
    let (iu, iv) = (u0 as usize, v0 as usize);
    let d = |du: usize, dv: usize| frame.depth[(iv + dv) * k.width + iu + du] as f64;
    let ds = [d(0, 0), d(1, 0), d(0, 1), d(1, 1)];
    let (lo, hi) = ds.iter().fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
    if lo <= 0.0 || hi - lo > 0.01 {
        return None;
    }
    let (fu, fv) = (u - u0, v - v0);
    Some(ds[0] * (1.0 - fu) * (1.0 - fv) + ds[1] * fu * (1.0 - fv) + ds[2] * (1.0 - fu) * fv + ds[3] * fu * fv)
}

#[test]
fn cameras_agree_where_they_overlap() {
    // Every point seen by camera A, projected into camera B: where B sees the same smooth surface
    // (its depth there is within 1 cm), B's interpolated depth must match to within 2 mm.
    let (_scene, mut world) = box_world();
    let mut rig = CameraRig::new(&world, 128, Visuals::Full).unwrap();
    let frames = render_all(&mut world, &mut rig);
    for a in &frames {
        let cloud = PointCloud::from_frame(a, Some(&flowram::sim::Workspace::TABLE));
        for b in frames.iter().filter(|b| b.camera != a.camera) {
            let world_to_b = b.extrinsics.inverse();
            let (mut compared, mut agree) = (0usize, 0usize);
            for p in &cloud.points {
                let pc = world_to_b * Point3::from(p.coords.cast::<f64>());
                if pc.z <= 0.05 {
                    continue;
                }
                let k = &b.intrinsics;
                let (u, v) = (k.fx * pc.x / pc.z + k.cx, k.fy * pc.y / pc.z + k.cy);
                let Some(d) = depth_at(b, u, v) else { continue };
                if (d - pc.z).abs() > 0.01 {
                    continue; // occluded in B, or a different surface
                }
                compared += 1;
                if (d - pc.z).abs() < 0.002 {
                    agree += 1;
                }
            }
            if compared >= 200 {
                let ratio = agree as f64 / compared as f64;
                assert!(
                    ratio > 0.95,
                    "{} vs {}: only {:.1}% of {compared} shared points agree within 2 mm",
                    a.camera,
                    b.camera,
                    ratio * 100.0
                );
            } else if a.camera != "wrist" && b.camera != "wrist" {
                panic!(
                    "{} and {} share only {compared} points; the fixed cameras must overlap on the table",
                    a.camera, b.camera
                );
            }
        }
    }
}

#[test]
fn rendering_is_deterministic() {
    let (_scene, mut world) = box_world();
    let mut rig = CameraRig::new(&world, 128, Visuals::Full).unwrap();
    let first = render_all(&mut world, &mut rig);
    // Move the arm and the box, come back to the same state, render again.
    world.reset_to("ready").unwrap();
    world.set_body_pose("probe_box", &Isometry3::translation(0.6, -0.2, 0.8)).unwrap();
    let _ = render_all(&mut world, &mut rig);
    world.reset_to("home").unwrap();
    world.set_body_pose("probe_box", &box_pose()).unwrap();
    let second = render_all(&mut world, &mut rig);
    for (a, b) in first.iter().zip(&second) {
        assert!(a.rgb == b.rgb, "camera {}: RGB differs between identical states", a.camera);
        assert!(a.depth == b.depth, "camera {}: depth differs between identical states", a.camera);
        assert!(a.rgb.iter().any(|&c| c != a.rgb[0]), "camera {}: blank image", a.camera);
    }
}

#[test]
fn camera_model_matches_the_scene() {
    let world = World::load_named("default").unwrap();
    let rig = CameraRig::new(&world, 128, Visuals::Full).unwrap();
    let front = rig.camera_index("front").unwrap();
    let k = rig.intrinsics(&world, front);
    // fovy 50 deg at 128 px: f = 64 / tan(25 deg).
    assert!((k.fy - 64.0 / 25f64.to_radians().tan()).abs() < 1e-9);
    assert_eq!((k.cx, k.cy), (63.5, 63.5));
    let pose = rig.extrinsics(&world, front);
    assert!((pose.translation.vector - Vector3::new(1.3, 0.0, 1.45)).norm() < 1e-9);
    // OpenCV axes: z forward toward the table (down and toward -x), y down in the image.
    let z = pose.rotation * Vector3::z();
    let y = pose.rotation * Vector3::y();
    assert!(z.x < -0.8 && z.z < -0.4, "front camera looks at the table: {z:?}");
    assert!(y.z < 0.0, "image y points down: {y:?}");
    let err = rig.camera_index("top").unwrap_err().to_string();
    assert!(err.contains("front, left_shoulder, right_shoulder, wrist"), "{err}");
}

#[test]
fn fast_visuals_change_only_the_robot() {
    let (_scene, mut world) = box_world();
    let mut full = CameraRig::new(&world, 128, Visuals::Full).unwrap();
    let mut fast = CameraRig::new(&world, 128, Visuals::Fast).unwrap();
    let i = full.camera_index("front").unwrap();
    let (a, b) = (full.render(&mut world, i).unwrap(), fast.render(&mut world, i).unwrap());
    let differing = a.depth.iter().zip(&b.depth).filter(|(x, y)| (*x - *y).abs() > 1e-4).count();
    assert!(differing > 0, "fast visuals draw the arm differently");
    // The box and the table are primitives: identical in both.
    let ca = PointCloud::from_frame(&a, None);
    let cb = PointCloud::from_frame(&b, None);
    let count_box = |c: &PointCloud| {
        c.points
            .iter()
            .filter(|p| {
                (box_pose().inverse() * p.cast::<f64>()).coords.abs().iter().zip(HALF).all(|(x, h)| *x <= h + 0.005)
            })
            .count()
    };
    assert_eq!(count_box(&ca), count_box(&cb));
}

/// Rigs made, drawn and dropped on several threads at once (as the harness runs tests, and as a
/// user rendering several worlds would) each render what one rig alone renders. The creation and
/// destruction of their GL contexts are serialised (`CameraRig`'s `GL_CONTEXTS`); a race there
/// would show as a crash or a wrong image.
#[test]
fn rigs_made_and_dropped_on_several_threads_at_once_render_as_one_alone() {
    let (_scene, mut world) = box_world();
    let front = CAMERAS[0];
    let reference = {
        let mut rig = CameraRig::new(&world, 64, Visuals::Fast).unwrap();
        rig.render(&mut world, rig.camera_index(front).unwrap()).unwrap()
    };
    std::thread::scope(|s| {
        for t in 0..4 {
            let reference = &reference;
            s.spawn(move || {
                let (_scene, mut world) = box_world();
                for round in 0..4 {
                    let mut rig = CameraRig::new(&world, 64, Visuals::Fast).unwrap();
                    let frame = rig.render(&mut world, rig.camera_index(front).unwrap()).unwrap();
                    assert!(
                        frame.rgb == reference.rgb && frame.depth == reference.depth,
                        "thread {t}, round {round}: the image differs from one rig's alone"
                    );
                }
            });
        }
    });
}
