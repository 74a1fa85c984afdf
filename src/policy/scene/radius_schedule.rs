//! The Dynamic Radius Schedule (DRS): the radius of the region around the current noisy action
//! position from which the geometric tokens are sampled, shrinking with flow time, and the
//! selection of those tokens. Radii are in normalised workspace units.
use serde::{Deserialize, Serialize};

use super::farthest_point::farthest_point_sample;
use crate::policy::error::{PolicyError, Result};

/// Distance between opposite corners of the normalised workspace [-1, 1]^3: a ball of this
/// radius around any point of the box covers the whole box.
pub const GLOBAL_RADIUS: f32 = 3.464_101_6; // 2 * sqrt(3)

/// Raw form of [`RadiusSchedule`] for deserialisation (validated on conversion).
#[derive(Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
enum RadiusScheduleSpec {
    Dynamic { r_min: f32, r_max: f32, power: f32 },
    Global,
}

/// The Dynamic Radius Schedule: radius `r(t)` (normalised workspace units) of the region around
/// the current noisy action position from which geometric tokens are sampled, for flow time `t`
/// (0 = noise, 1 = data).
///
/// JSON: `{"kind": "dynamic", "r_min": 0.4, "r_max": 3.4641016, "power": 1.0}` or
/// `{"kind": "global"}`; deserialisation validates like [`RadiusSchedule::dynamic`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RadiusScheduleSpec", tag = "kind", rename_all = "snake_case")]
pub enum RadiusSchedule {
    /// `r(t) = r_min + (r_max - r_min) (1 - t)^power`: `r_max` (global, >= 2 sqrt(3)) at t = 0,
    /// shrinking monotonically to `r_min` at t = 1.
    Dynamic { r_min: f32, r_max: f32, power: f32 },
    /// The "w/o DRS" ablation: global sampling at every step.
    Global,
}

impl TryFrom<RadiusScheduleSpec> for RadiusSchedule {
    type Error = PolicyError;
    fn try_from(spec: RadiusScheduleSpec) -> Result<Self> {
        match spec {
            RadiusScheduleSpec::Dynamic { r_min, r_max, power } => Self::dynamic(r_min, r_max, power),
            RadiusScheduleSpec::Global => Ok(Self::Global),
        }
    }
}

impl Default for RadiusSchedule {
    /// `r_min = 0.4, r_max = 2 sqrt(3), power = 1` (see [`RadiusSchedule::DEFAULT_R_MIN`],
    /// [`RadiusSchedule::DEFAULT_POWER`]).
    fn default() -> Self {
        Self::Dynamic { r_min: Self::DEFAULT_R_MIN, r_max: GLOBAL_RADIUS, power: Self::DEFAULT_POWER }
    }
}

impl RadiusSchedule {
    /// Radius at t = 1 (normalised units). On flowram's table workspace (1.15 x 1.3 x 0.66 m)
    /// that is about 23 x 26 x 13 cm: the gripper and what it is about to touch. The code
    /// release uses a fixed 1.2 once out of the noisiest 10 % of the flow; 0.4 is reached only
    /// at the end, when the action estimate is precise.
    pub const DEFAULT_R_MIN: f32 = 0.4;
    /// Linear shrinking: the noisy position is `a_t = t a1 + (1 - t) a0`, so its distance to the
    /// target position is `(1 - t) |a1 - a0|`, linear in t (clamping the centre to the box only
    /// brings it closer). With power 1 the region contains the target at every t whenever
    /// `|a1 - a0| <= r_max - r_min` (3.06 with the defaults): about 97 % of the 3D Gaussian
    /// noise draws for a target at the workspace centre, about 80 % at a corner.
    pub const DEFAULT_POWER: f32 = 1.0;

    /// A validated dynamic schedule. Errors: [`PolicyError::Invalid`] unless all values are
    /// finite, `0 < r_min <= r_max`, `r_max >= 2 sqrt(3)` (global at t = 0) and `power > 0`.
    pub fn dynamic(r_min: f32, r_max: f32, power: f32) -> Result<Self> {
        if !(r_min.is_finite() && r_max.is_finite() && power.is_finite()) {
            return Err(PolicyError::Invalid(format!(
                "radius schedule needs finite values; got r_min {r_min}, r_max {r_max}, power {power}"
            )));
        }
        if !(r_min > 0.0 && r_min <= r_max) {
            return Err(PolicyError::Invalid(format!(
                "radius schedule needs 0 < r_min <= r_max (normalised workspace units); got r_min {r_min}, r_max {r_max}"
            )));
        }
        if r_max < GLOBAL_RADIUS {
            return Err(PolicyError::Invalid(format!(
                "radius schedule r_max {r_max} must be >= 2 sqrt(3) = {GLOBAL_RADIUS} so that sampling is global at t = 0"
            )));
        }
        if power <= 0.0 {
            return Err(PolicyError::Invalid(format!("radius schedule power must be > 0; got {power}")));
        }
        Ok(Self::Dynamic { r_min, r_max, power })
    }

    /// Checks a schedule built by hand (the enum fields are public).
    pub fn validate(&self) -> Result<()> {
        match *self {
            Self::Dynamic { r_min, r_max, power } => Self::dynamic(r_min, r_max, power).map(|_| ()),
            Self::Global => Ok(()),
        }
    }

    /// `r(t)` in normalised workspace units, `t` clamped to [0, 1]; infinite for `Global`.
    /// Continuous and non-increasing in t.
    pub fn radius(&self, t: f32) -> f32 {
        match *self {
            Self::Dynamic { r_min, r_max, power } => {
                let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
                r_min + (r_max - r_min) * (1.0 - t).powf(power)
            }
            Self::Global => f32::INFINITY,
        }
    }
}

/// Which points become geometric tokens at one flow step.
#[derive(Debug, Clone, PartialEq)]
pub struct GeometricSelection {
    /// Exactly `n2` indices into the cloud (fewer only when the cloud itself is smaller; see
    /// [`select_geometric_tokens`]).
    pub indices: Vec<usize>,
    /// The radius `r(t)` used (normalised units; infinite for the global schedule).
    pub radius: f32,
    /// True when fewer than `min_inside` points lay within the radius and global sampling was
    /// used instead.
    pub fell_back: bool,
}

/// Picks `n2` geometric tokens from `points_norm` (normalised workspace coordinates, [-1, 1]^3)
/// around `center` (the current noisy action position, normalised) at flow time `t` in [0, 1]:
///
/// 1. `center` is clamped to [-1, 1]^3 (early in the flow the noisy position can lie outside
///    the workspace; the gripper's target cannot), and `r = schedule.radius(t)`.
/// 2. If `r >= 2 sqrt(3)` (always at t = 0, and always for [`RadiusSchedule::Global`]), every
///    point is a candidate: global sampling.
/// 3. Otherwise the candidates are the points with `|p - center| <= r`, in index order.
///    - at least `n2` of them: farthest point sampling over them to `n2`, starting from the
///      lowest index;
///    - between `min_inside` and `n2 - 1`: all of them, repeated cyclically to `n2`
///      (`c0 c1 .. ck c0 c1 ..`), so that the token count is fixed;
///    - fewer than `min_inside`: global sampling, `fell_back = true`.
/// 4. Global sampling is farthest point sampling from index 0 over the whole cloud (so at t = 0
///    the selection equals `farthest_point_sample(points_norm, n2, 0)`), or every index repeated
///    cyclically when the cloud has fewer than `n2` points.
///
/// Deterministic. Errors: [`PolicyError::Invalid`] for an empty cloud, `n2 == 0`,
/// `min_inside == 0`, a non-finite `center` or `t` outside [0, 1], non-finite points, or an
/// invalid schedule.
pub fn select_geometric_tokens(
    points_norm: &[[f32; 3]],
    center: [f32; 3],
    t: f32,
    n2: usize,
    min_inside: usize,
    schedule: &RadiusSchedule,
) -> Result<GeometricSelection> {
    select_geometric_tokens_cached(points_norm, None, center, t, n2, min_inside, schedule)
}

/// [`select_geometric_tokens`] with the global selection of these points computed once
/// ([`global_geometric_tokens`] with the same `n2`; inference reuses it at every step that
/// samples globally: t = 0, the w/o-DRS ablation, the fallback, and radii that hold every point).
/// The result is identical to [`select_geometric_tokens`]'s. A `global` of another length than
/// `n2` is ignored.
pub fn select_geometric_tokens_cached(
    points_norm: &[[f32; 3]],
    global: Option<&[usize]>,
    center: [f32; 3],
    t: f32,
    n2: usize,
    min_inside: usize,
    schedule: &RadiusSchedule,
) -> Result<GeometricSelection> {
    let global_indices = || match global {
        Some(g) if g.len() == n2 => Ok(g.to_vec()),
        _ => global_geometric_tokens(points_norm, n2),
    };
    if points_norm.is_empty() {
        return Err(PolicyError::Invalid("geometric tokens need a non-empty point cloud".into()));
    }
    if n2 == 0 || min_inside == 0 {
        return Err(PolicyError::Invalid(format!(
            "geometric token count n2 ({n2}) and min_inside ({min_inside}) must be positive"
        )));
    }
    if !center.iter().all(|v| v.is_finite()) {
        return Err(PolicyError::Invalid(format!("action position {center:?} is not finite")));
    }
    if !(0.0..=1.0).contains(&t) {
        return Err(PolicyError::Invalid(format!("flow time t = {t} must lie in [0, 1]")));
    }
    schedule.validate()?;
    let radius = schedule.radius(t);
    if radius >= GLOBAL_RADIUS {
        return Ok(GeometricSelection { indices: global_indices()?, radius, fell_back: false });
    }

    let center = center.map(|v| v.clamp(-1.0, 1.0));
    let radius2 = radius * radius;
    let inside: Vec<usize> = (0..points_norm.len())
        .filter(|&i| {
            let p = points_norm[i];
            let d = [p[0] - center[0], p[1] - center[1], p[2] - center[2]];
            d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= radius2
        })
        .collect();

    if inside.len() < min_inside {
        return Ok(GeometricSelection { indices: global_indices()?, radius, fell_back: true });
    }
    let indices = if inside.len() == points_norm.len() {
        // every point inside: FPS over the same candidates from the same start
        global_indices()?
    } else if inside.len() >= n2 {
        let local: Vec<[f32; 3]> = inside.iter().map(|&i| points_norm[i]).collect();
        farthest_point_sample(&local, n2, 0)?.into_iter().map(|k| inside[k]).collect()
    } else {
        inside.iter().copied().cycle().take(n2).collect()
    };
    Ok(GeometricSelection { indices, radius, fell_back: false })
}

/// `n2` indices sampled over the whole cloud: farthest point sampling from index 0 (cyclic
/// repetition when the cloud is smaller than `n2`). The geometric tokens at t = 0.
pub fn global_geometric_tokens(points_norm: &[[f32; 3]], n2: usize) -> Result<Vec<usize>> {
    if points_norm.len() >= n2 {
        farthest_point_sample(points_norm, n2, 0)
    } else {
        Ok((0..points_norm.len()).cycle().take(n2).collect())
    }
}

// ---------------------------------------------------------------------------------------------
// 3D positional encoding
// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_cloud(rng: &mut ChaCha8Rng, n: usize) -> Vec<[f32; 3]> {
        (0..n).map(|_| std::array::from_fn(|_| rng.random_range(-1.0f32..1.0))).collect()
    }

    #[test]
    fn radius_schedule_is_global_then_shrinks_monotonically() {
        let schedule = RadiusSchedule::default();
        schedule.validate().unwrap();
        assert!(schedule.radius(0.0) >= GLOBAL_RADIUS);
        assert!((schedule.radius(1.0) - RadiusSchedule::DEFAULT_R_MIN).abs() < 1e-6);
        let mut previous = f32::INFINITY;
        for k in 0..=1000 {
            let r = schedule.radius(k as f32 / 1000.0);
            assert!(r <= previous, "r(t) must not increase");
            assert!(previous == f32::INFINITY || previous - r < 0.01, "r(t) must be continuous");
            previous = r;
        }
        let quadratic = RadiusSchedule::dynamic(0.2, 4.0, 2.0).unwrap();
        assert!((quadratic.radius(0.5) - (0.2 + 3.8 * 0.25)).abs() < 1e-6);
        assert_eq!(RadiusSchedule::Global.radius(0.9), f32::INFINITY);
        for (r_min, r_max, power) in
            [(0.0, 4.0, 1.0), (0.5, 3.0, 1.0), (5.0, 4.0, 1.0), (0.5, 4.0, 0.0), (f32::NAN, 4.0, 1.0)]
        {
            assert!(RadiusSchedule::dynamic(r_min, r_max, power).is_err(), "{r_min} {r_max} {power}");
        }
        let json = serde_json::to_string(&schedule).unwrap();
        assert_eq!(serde_json::from_str::<RadiusSchedule>(&json).unwrap(), schedule);
        assert_eq!(serde_json::from_str::<RadiusSchedule>(r#"{"kind":"global"}"#).unwrap(), RadiusSchedule::Global);
        assert!(
            serde_json::from_str::<RadiusSchedule>(r#"{"kind":"dynamic","r_min":0.4,"r_max":1.0,"power":1}"#).is_err()
        );
    }

    #[test]
    fn cached_global_selection_gives_the_same_tokens() {
        let mut rng = ChaCha8Rng::seed_from_u64(23);
        let cloud = random_cloud(&mut rng, 3000);
        let global = global_geometric_tokens(&cloud, 256).unwrap();
        let wrong_length = global_geometric_tokens(&cloud, 100).unwrap();
        for schedule in [RadiusSchedule::default(), RadiusSchedule::Global] {
            // t = 0 (global), every point inside (r ~ 3.3), a local ball, the fallback (far centre)
            for (center, t) in
                [([0.1, 0.2, -0.3], 0.0), ([0.0, 0.0, 0.0], 0.05), ([0.2, -0.3, 0.1], 0.7), ([3.0, 3.0, 3.0], 1.0)]
            {
                let plain = select_geometric_tokens(&cloud, center, t, 256, 32, &schedule).unwrap();
                for g in [&global, &wrong_length] {
                    let cached =
                        select_geometric_tokens_cached(&cloud, Some(g), center, t, 256, 32, &schedule).unwrap();
                    assert_eq!(cached, plain, "t {t}, centre {center:?}, {schedule:?}");
                }
            }
        }
    }

    #[test]
    fn geometric_tokens_lie_within_the_radius() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let cloud = random_cloud(&mut rng, 4096);
        let schedule = RadiusSchedule::default();
        let center = [0.2, -0.3, 0.1];
        for t in [0.5f32, 0.7, 0.8] {
            let selection = select_geometric_tokens(&cloud, center, t, 256, 32, &schedule).unwrap();
            assert!(!selection.fell_back);
            assert_eq!(selection.indices.len(), 256);
            assert!((selection.radius - schedule.radius(t)).abs() < 1e-6);
            let mut unique = selection.indices.clone();
            unique.sort_unstable();
            unique.dedup();
            assert_eq!(unique.len(), 256, "enough points inside: no repetition");
            for &i in &selection.indices {
                let p = cloud[i];
                let d = ((p[0] - center[0]).powi(2) + (p[1] - center[1]).powi(2) + (p[2] - center[2]).powi(2)).sqrt();
                assert!(d <= selection.radius + 1e-6, "token {i} at distance {d} > r = {}", selection.radius);
            }
            assert_eq!(
                select_geometric_tokens(&cloud, center, t, 256, 32, &schedule).unwrap(),
                selection,
                "deterministic"
            );
        }
    }

    #[test]
    fn geometric_tokens_are_global_fps_at_t0_and_without_drs() {
        let mut rng = ChaCha8Rng::seed_from_u64(22);
        let cloud = random_cloud(&mut rng, 3000);
        let global = farthest_point_sample(&cloud, 512, 0).unwrap();
        for center in [[0.0f32; 3], [0.9, -0.9, 0.9], [5.0, 5.0, -7.0]] {
            let at_noise = select_geometric_tokens(&cloud, center, 0.0, 512, 16, &RadiusSchedule::default()).unwrap();
            assert_eq!(at_noise.indices, global);
            assert!(!at_noise.fell_back);
            let without_drs = select_geometric_tokens(&cloud, center, 0.95, 512, 16, &RadiusSchedule::Global).unwrap();
            assert_eq!(without_drs.indices, global);
        }
    }

    #[test]
    fn geometric_tokens_clamp_the_centre_and_stay_global_for_uncropped_points() {
        let mut rng = ChaCha8Rng::seed_from_u64(24);
        let mut cloud = random_cloud(&mut rng, 3000);
        // A noisy action far outside the workspace samples around the nearest box corner.
        let schedule = RadiusSchedule::default();
        let far = select_geometric_tokens(&cloud, [3.0, 3.0, 3.0], 0.5, 256, 16, &schedule).unwrap();
        let corner = select_geometric_tokens(&cloud, [1.0, 1.0, 1.0], 0.5, 256, 16, &schedule).unwrap();
        assert!(!far.fell_back);
        assert_eq!(far, corner);
        // Points outside [-1, 1]^3 (a caller that did not crop) still count at t = 0.
        cloud.extend([[-1.6f32, -1.6, -1.6], [1.7, 1.7, -1.7]]);
        let global = farthest_point_sample(&cloud, 256, 0).unwrap();
        let at_noise = select_geometric_tokens(&cloud, [0.9, 0.9, 0.9], 0.0, 256, 16, &schedule).unwrap();
        assert_eq!(at_noise.indices, global);
        assert!(global.contains(&3000) && global.contains(&3001));
    }

    #[test]
    fn geometric_tokens_fall_back_or_repeat_when_few_points_are_near() {
        let mut rng = ChaCha8Rng::seed_from_u64(23);
        // Most points in a blob around (-0.8, -0.8, -0.8), 20 around (0.8, 0.8, 0.8).
        let mut cloud: Vec<[f32; 3]> =
            (0..2000).map(|_| std::array::from_fn(|_| -0.8 + rng.random_range(-0.1f32..0.1))).collect();
        cloud.extend((0..20).map(|_| std::array::from_fn::<f32, 3, _>(|_| 0.8 + rng.random_range(-0.05f32..0.05))));
        let schedule = RadiusSchedule::default();
        let far = [0.8, 0.8, 0.8];
        // 20 points inside, min_inside 32: fall back to global FPS.
        let fallback = select_geometric_tokens(&cloud, far, 1.0, 256, 32, &schedule).unwrap();
        assert!(fallback.fell_back);
        assert_eq!(fallback.indices, farthest_point_sample(&cloud, 256, 0).unwrap());
        // min_inside 10: the 20 points repeated cyclically to 256.
        let padded = select_geometric_tokens(&cloud, far, 1.0, 256, 10, &schedule).unwrap();
        assert!(!padded.fell_back);
        assert_eq!(padded.indices.len(), 256);
        let inside: Vec<usize> = (2000..2020).collect();
        assert_eq!(&padded.indices[..20], &inside[..]);
        assert_eq!(&padded.indices[20..40], &inside[..]);
        // Exact count n2 for any centre and time.
        for _ in 0..50 {
            let center: [f32; 3] = std::array::from_fn(|_| rng.random_range(-2.0f32..2.0));
            let t = rng.random_range(0.0f32..=1.0);
            let s = select_geometric_tokens(&cloud, center, t, 300, 8, &schedule).unwrap();
            assert_eq!(s.indices.len(), 300);
        }
        // A cloud smaller than n2 is repeated; bad arguments are refused.
        assert_eq!(select_geometric_tokens(&cloud[..5], far, 0.0, 12, 1, &schedule).unwrap().indices.len(), 12);
        assert!(select_geometric_tokens(&[], far, 0.5, 12, 1, &schedule).is_err());
        assert!(select_geometric_tokens(&cloud, far, 1.5, 12, 1, &schedule).is_err());
        assert!(select_geometric_tokens(&cloud, [f32::NAN; 3], 0.5, 12, 1, &schedule).is_err());
        assert!(select_geometric_tokens(&cloud, far, 0.5, 0, 1, &schedule).is_err());
        let bad = RadiusSchedule::Dynamic { r_min: 0.4, r_max: 1.0, power: 1.0 };
        assert!(select_geometric_tokens(&cloud, far, 0.5, 12, 1, &bad).is_err());
    }
}
