//! Build script: finds the native dependencies installed by `scripts/setup.sh`, compiles the
//! small C++ shim over Pinocchio (`src/robot/shim/`, -O2, no debug info, rebuilt only when it
//! changes), and bakes rpaths to libmujoco and libpinocchio into every binary and test, so
//! nothing needs `LD_LIBRARY_PATH` at run time.
use std::path::{Path, PathBuf};

const SHIM_SOURCES: [&str; 2] = ["src/robot/shim/fr_pin_arm_build.cpp", "src/robot/shim/fr_pin_arm_compute.cpp"];
const SHIM_HEADERS: [&str; 2] = ["src/robot/shim/fr_pin_arm.h", "src/robot/shim/fr_pin_arm_impl.hpp"];

fn main() {
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    for var in ["FLOWRAM_DEPS", "MUJOCO_DYNAMIC_LINK_DIR", "PINOCCHIO_PREFIX"] {
        println!("cargo::rerun-if-env-changed={var}");
    }
    println!("cargo::rerun-if-changed=build.rs");
    for f in SHIM_SOURCES.iter().chain(&SHIM_HEADERS) {
        println!("cargo::rerun-if-changed={f}");
    }

    let deps = std::env::var_os("FLOWRAM_DEPS").map(PathBuf::from).unwrap_or_else(|| root.join(".deps"));
    println!("cargo::rustc-env=FLOWRAM_BUILD_DEPS_DIR={}", deps.display());

    let mujoco_lib =
        std::env::var_os("MUJOCO_DYNAMIC_LINK_DIR").map(PathBuf::from).unwrap_or_else(|| deps.join("mujoco/lib"));
    let pinocchio = std::env::var_os("PINOCCHIO_PREFIX")
        .map(PathBuf::from)
        .unwrap_or_else(|| deps.join("venv/lib/python3.11/site-packages/cmeel.prefix"));
    let missing = [
        (mujoco_lib.join("libmujoco.so"), "MUJOCO_DYNAMIC_LINK_DIR (the folder holding libmujoco.so)"),
        (
            pinocchio.join("lib/libpinocchio_default.so"),
            "PINOCCHIO_PREFIX (the cmeel.prefix holding lib/ and include/)",
        ),
        (pinocchio.join("include/eigen3/Eigen/Core"), "PINOCCHIO_PREFIX (Eigen headers from cmeel-eigen)"),
    ];
    let mut ok = true;
    for (file, var) in &missing {
        if !file.is_file() {
            println!("cargo::error={} not found. Run scripts/setup.sh first, or set {var}.", file.display());
            ok = false;
        }
    }
    if !ok {
        return;
    }
    build_pinocchio_shim(&pinocchio);
    // rpaths for every target of this package (lib tests, bin, integration tests).
    println!("cargo::rustc-link-arg=-Wl,-rpath,{}", mujoco_lib.display());
    println!("cargo::rustc-link-arg=-Wl,-rpath,{}", pinocchio.join("lib").display());
}

fn build_pinocchio_shim(prefix: &Path) {
    let include = prefix.join("include");
    cc::Build::new()
        .cpp(true)
        .std("c++17")
        .opt_level(2)
        .debug(false)
        .warnings(false)
        .include("src/robot/shim")
        .include(&include)
        .include(include.join("eigen3"))
        // Must match how libpinocchio_default was built (its pinocchioTargets.cmake).
        .define("PINOCCHIO_ENABLE_TEMPLATE_INSTANTIATION", None)
        .define("BOOST_MPL_LIMIT_LIST_SIZE", "30")
        .define("BOOST_MPL_LIMIT_VECTOR_SIZE", "30")
        .define("BOOST_MPL_CFG_NO_PREPROCESSED_HEADERS", None)
        .define("BOOST_FUSION_INVOKE_MAX_ARITY", "12")
        // The wheel is a release build; without NDEBUG a failing header assertion would abort()
        // through the C boundary.
        .define("NDEBUG", None)
        .files(SHIM_SOURCES)
        .compile("fr_pin_arm");
    println!("cargo::rustc-link-search=native={}", prefix.join("lib").display());
    println!("cargo::rustc-link-lib=dylib=pinocchio_default");
}
