//! Summary statistics of measurements (benchmark repeats, per-keyframe errors).

/// Median (mean of the middle two for an even count; 0 for none).
pub fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return 0.0;
    }
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}

/// The 95 % Wilson score interval of a success rate: `successes` of `trials` (both bounds 0 for
/// no trials). Unlike the normal approximation it stays inside [0, 1] and is informative at 0 or
/// `trials` successes, which small closed-loop evaluations often give.
pub fn wilson_interval(successes: usize, trials: usize) -> [f64; 2] {
    if trials == 0 {
        return [0.0, 0.0];
    }
    const Z: f64 = 1.959_963_984_540_054; // the 97.5 % quantile of the standard normal
    let n = trials as f64;
    let p = successes as f64 / n;
    let z2 = Z * Z;
    let centre = (p + z2 / (2.0 * n)) / (1.0 + z2 / n);
    let half = Z / (1.0 + z2 / n) * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt();
    [(centre - half).max(0.0), (centre + half).min(1.0)]
}

/// The exact two-sided McNemar test of two policies run on the same seeds: `only_a` seeds that
/// only the first solved and `only_b` that only the second solved (the seeds both or neither
/// solved carry no information about which is better). Returns the p-value of "equally good":
/// twice the binomial(n, 1/2) tail of the smaller count, at most 1.
pub fn mcnemar_exact_p(only_a: usize, only_b: usize) -> f64 {
    let n = only_a + only_b;
    if n == 0 {
        return 1.0;
    }
    let k = only_a.min(only_b);
    // sum_{i <= k} C(n, i) / 2^n, in logs so that large n stays finite
    let ln_choose = |i: usize| -> f64 { (1..=i).map(|j| ((n - i + j) as f64 / j as f64).ln()).sum() };
    let tail: f64 = (0..=k).map(|i| (ln_choose(i) - n as f64 * std::f64::consts::LN_2).exp()).sum();
    (2.0 * tail).min(1.0)
}

/// The `p` quantile (0..=1) of ascending-sorted `sorted`, nearest rank (0 for none).
pub fn percentile_sorted(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    sorted[((sorted.len() - 1) as f64 * p.clamp(0.0, 1.0)).round() as usize]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mcnemar_matches_the_binomial_tail() {
        // 0 vs 6 discordant seeds: 2 / 64
        assert!((mcnemar_exact_p(0, 6) - 2.0 / 64.0).abs() < 1e-12);
        // 1 vs 9: 2 (1 + 10) / 1024
        assert!((mcnemar_exact_p(9, 1) - 22.0 / 1024.0).abs() < 1e-12);
        assert_eq!(mcnemar_exact_p(3, 3), 1.0);
        assert_eq!(mcnemar_exact_p(0, 0), 1.0);
        assert!(mcnemar_exact_p(0, 400) < 1e-100);
    }

    #[test]
    fn wilson_interval_matches_published_values() {
        // 8 of 10: [0.490, 0.943]; 0 of 10: [0, 0.278]; 50 of 50: [0.929, 1] (Wilson 1927 /
        // any statistics table).
        let close = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).abs() < 1e-3 && (a[1] - b[1]).abs() < 1e-3;
        assert!(close(wilson_interval(8, 10), [0.490, 0.943]), "{:?}", wilson_interval(8, 10));
        assert!(close(wilson_interval(0, 10), [0.0, 0.278]), "{:?}", wilson_interval(0, 10));
        assert!(close(wilson_interval(50, 50), [0.929, 1.0]), "{:?}", wilson_interval(50, 50));
        assert_eq!(wilson_interval(0, 0), [0.0, 0.0]);
    }

    #[test]
    fn median_of_odd_even_and_empty() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), 2.5);
        assert_eq!(median(&[]), 0.0);
    }
}
