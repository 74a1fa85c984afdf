//! The order of point tokens in the causal scan. A selective scan reads its sequence once, in
//! order, so the order decides which tokens meet in its state and its local convolution:
//!
//! - semantic tokens follow a Z-order (Morton) curve through the normalised workspace, so that
//!   points close in space are close in the sequence and an object's points form a run the scan
//!   can summarise (farthest point sampling alone leaves them scattered over the whole
//!   sequence; PointMamba's serialisation makes the same point);
//! - geometric tokens run from the farthest to the nearest to the current action position, so
//!   the points where the gripper is about to go come last, right before the action token that
//!   reads them.
//!
//! Both orders are deterministic (ties by index) and the same in training and inference.

/// Bits per axis of the Morton code (a 1024^3 grid over [-1, 1]^3: ~1 mm cells for a 1 m box).
const MORTON_BITS: u32 = 10;

/// Spreads the low 10 bits of `v` to every third bit.
fn spread_bits(v: u32) -> u64 {
    let mut x = u64::from(v & 0x3ff);
    x = (x | (x << 16)) & 0x0300_00ff;
    x = (x | (x << 8)) & 0x0300_f00f;
    x = (x | (x << 4)) & 0x030c_30c3;
    x = (x | (x << 2)) & 0x0924_9249;
    x
}

/// The Morton code of a point in normalised coordinates (clamped to [-1, 1]^3; z is the most
/// significant axis, so runs are horizontal slabs first).
pub fn morton_code(p: [f32; 3]) -> u64 {
    let cells = (1u32 << MORTON_BITS) as f32;
    let q = p.map(|v| (((v.clamp(-1.0, 1.0) + 1.0) * 0.5 * cells) as u32).min((1 << MORTON_BITS) - 1));
    spread_bits(q[0]) | (spread_bits(q[1]) << 1) | (spread_bits(q[2]) << 2)
}

/// Sorts `indices` (into `points`) along the Z-order curve; ties by index.
pub fn sort_by_morton(points: &[[f32; 3]], indices: &mut [usize]) {
    indices.sort_by_key(|&i| (morton_code(points[i]), i));
}

/// Sorts `indices` (into `points`) from the farthest to the nearest to `center`; ties by index.
pub fn sort_far_to_near(points: &[[f32; 3]], center: [f32; 3], indices: &mut [usize]) {
    let d2 = |i: usize| -> f32 { (0..3).map(|a| (points[i][a] - center[a]).powi(2)).sum() };
    indices.sort_by(|&a, &b| d2(b).total_cmp(&d2(a)).then(a.cmp(&b)));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn morton_order_keeps_neighbours_together() {
        // two clusters far apart, interleaved in the input: sorted, each forms one run
        let mut points = Vec::new();
        for k in 0..50 {
            let e = k as f32 * 1e-3;
            points.push([-0.8 + e, -0.7, 0.1 + e]);
            points.push([0.6 - e, 0.5, -0.2]);
        }
        let mut order: Vec<usize> = (0..points.len()).collect();
        sort_by_morton(&points, &mut order);
        let cluster = |i: usize| points[i][0] < 0.0;
        let switches = order.windows(2).filter(|w| cluster(w[0]) != cluster(w[1])).count();
        assert_eq!(switches, 1, "each cluster must be one run");
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..points.len()).collect::<Vec<_>>(), "a permutation");
        // codes: monotone in each axis alone, z most significant, clamped outside the box
        assert!(morton_code([0.0, 0.0, -1.0]) < morton_code([0.0, 0.0, 1.0]));
        assert!(morton_code([1.0, 1.0, -0.01]) < morton_code([-1.0, -1.0, 0.01]));
        assert_eq!(morton_code([5.0, -5.0, 2.0]), morton_code([1.0, -1.0, 1.0]));
        assert_eq!(morton_code([1.0, 1.0, 1.0]), (1u64 << 30) - 1);
        assert_eq!(morton_code([-1.0, -1.0, -1.0]), 0);
    }

    #[test]
    fn far_to_near_puts_the_nearest_last_with_ties_by_index() {
        let points = [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.9, 0.0], [0.0, -0.5, 0.0], [0.1, 0.0, 0.0]];
        let mut order = vec![0, 1, 2, 3, 4];
        sort_far_to_near(&points, [0.0, 0.0, 0.0], &mut order);
        assert_eq!(order, vec![2, 1, 3, 4, 0]);
        // duplicates (cyclic padding) stay together
        let mut padded = vec![4, 0, 4, 0];
        sort_far_to_near(&points, [0.0, 0.0, 0.0], &mut padded);
        assert_eq!(padded, vec![4, 4, 0, 0]);
    }
}
