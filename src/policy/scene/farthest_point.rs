//! Exact farthest point sampling (FPS) of point clouds, on a kd-tree of SIMD leaves.
use crate::policy::error::{PolicyError, Result};

/// SIMD width the leaf kernel is written for (16 f32 = one AVX-512 register, two AVX2).
const LANES: usize = 16;
/// Points per kd-tree leaf (about; leaves are padded to a multiple of [`LANES`]).
const LEAF_POINTS: usize = 64;
/// Subtrees at least this large are built in parallel (rayon::join on the two halves).
const PARALLEL_BUILD_MIN_POINTS: usize = 1 << 15;

/// Exact farthest point sampling: starting from `points[first]`, repeatedly picks the point whose
/// squared distance to the nearest already-picked point is largest (ties: the lowest index).
/// Returns `n` indices in pick order, `first` first. When `n >= points.len()`, returns all
/// indices `0..points.len()` in index order (no sampling needed); an empty cloud gives an empty
/// list.
///
/// The result is identical to the textbook O(N n) loop (same f32 arithmetic, same tie rule);
/// it is computed on a kd-tree of leaves (structure of arrays, a vectorised 16-lane kernel) where
/// a whole subtree is skipped when the new pick is no closer to its bounding box than its
/// current largest distance. The tree build (median splits over contiguous point records) is
/// rayon-parallel for subtrees of 2^15 points and more; the pick loop is serial (see the
/// module's benchmark: per-pick synchronisation of threads costs more than it saves). Several
/// clouds (a batch) are best sampled in parallel by the caller.
///
/// Errors: [`PolicyError::Invalid`] when `first >= points.len()` (non-empty cloud) or a
/// coordinate is not finite.
pub fn farthest_point_sample(points: &[[f32; 3]], n: usize, first: usize) -> Result<Vec<usize>> {
    if points.is_empty() || n == 0 {
        return Ok(Vec::new());
    }
    if first >= points.len() {
        return Err(PolicyError::Invalid(format!(
            "farthest point sampling starts at index {first}, but the cloud has {} points",
            points.len()
        )));
    }
    if let Some(bad) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(PolicyError::Invalid(format!(
            "point {bad} of the cloud is {:?}: farthest point sampling needs finite coordinates",
            points[bad]
        )));
    }
    if n >= points.len() {
        return Ok((0..points.len()).collect());
    }
    Ok(fps_dispatch(points, n, first))
}

fn fps_dispatch(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports AVX-512F (checked just above).
            return unsafe { fps_avx512(points, n, first) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            return unsafe { fps_avx2(points, n, first) };
        }
    }
    fps_generic(points, n, first)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn fps_avx512(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
    fps_generic(points, n, first)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn fps_avx2(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
    fps_generic(points, n, first)
}

/// The pick loop; compiled once per instruction set by the wrappers above.
#[inline(always)]
fn fps_generic(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
    let mut tree = FpsTree::build(points);
    let mut picks = Vec::with_capacity(n);
    picks.push(first);
    let mut last = points[first];
    for _ in 1..n {
        tree.update(1, last);
        let pick = tree.lowest_id_at(1, tree.node_max[1]) as usize;
        picks.push(pick);
        last = points[pick];
    }
    picks
}

/// One point of the cloud with its index, moved around while the tree is built.
#[derive(Clone, Copy)]
struct PointRecord {
    p: [f32; 3],
    id: u32,
}

fn bounding_box(records: &[PointRecord]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for r in records {
        for a in 0..3 {
            lo[a] = lo[a].min(r.p[a]);
            hi[a] = hi[a].max(r.p[a]);
        }
    }
    (lo, hi)
}

/// Orders `records` into `2^depth` spatially compact leaves: split at the middle position
/// (`len / 2`) along the widest axis of the bounding box, recursively. The leaf boundaries
/// depend only on the length, see [`leaf_bounds`].
fn kd_partition(records: &mut [PointRecord], depth: usize) {
    if depth == 0 || records.len() < 2 {
        return;
    }
    let (lo, hi) = bounding_box(records);
    let axis = (0..3).max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b]))).unwrap_or(0);
    let mid = records.len() / 2;
    records.select_nth_unstable_by(mid, |a, b| a.p[axis].total_cmp(&b.p[axis]).then(a.id.cmp(&b.id)));
    let (left, right) = records.split_at_mut(mid);
    if left.len() + right.len() >= PARALLEL_BUILD_MIN_POINTS {
        rayon::join(|| kd_partition(left, depth - 1), || kd_partition(right, depth - 1));
    } else {
        kd_partition(left, depth - 1);
        kd_partition(right, depth - 1);
    }
}

/// Start positions of the `2^depth` leaves of [`kd_partition`] over `len` records, plus `len`.
fn leaf_bounds(len: usize, depth: usize) -> Vec<usize> {
    let mut bounds = vec![0, len];
    for _ in 0..depth {
        let mut next = Vec::with_capacity(bounds.len() * 2);
        for w in bounds.windows(2) {
            next.extend([w[0], w[0] + (w[1] - w[0]) / 2]);
        }
        next.push(len);
        bounds = next;
    }
    bounds
}

/// A complete binary kd-tree (heap layout: node 1 is the root, node k has children 2k, 2k+1,
/// leaves are nodes `first_leaf..2 * first_leaf`). Points are stored leaf by leaf as structure
/// of arrays, each leaf padded to a multiple of [`LANES`] with copies of its first point whose
/// distance is -inf (never picked, never changed).
struct FpsTree {
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    /// Squared distance of each point to its nearest pick so far (+inf before the first).
    dist: Vec<f32>,
    ids: Vec<u32>,
    /// `leaf_range[l] .. leaf_range[l + 1]` are leaf l's (padded) slots.
    leaf_range: Vec<usize>,
    first_leaf: usize,
    node_lo: Vec<[f32; 3]>,
    node_hi: Vec<[f32; 3]>,
    /// Largest `dist` in each node's subtree.
    node_max: Vec<f32>,
}

impl FpsTree {
    fn build(points: &[[f32; 3]]) -> Self {
        let mut depth = 0;
        while points.len() > LEAF_POINTS << depth {
            depth += 1;
        }
        let first_leaf = 1usize << depth;
        let mut records: Vec<PointRecord> =
            points.iter().enumerate().map(|(i, &p)| PointRecord { p, id: i as u32 }).collect();
        kd_partition(&mut records, depth);
        let bounds = leaf_bounds(records.len(), depth);
        let padded_len: usize = bounds.windows(2).map(|w| (w[1] - w[0]).div_ceil(LANES) * LANES).sum();
        let mut tree = Self {
            xs: Vec::with_capacity(padded_len),
            ys: Vec::with_capacity(padded_len),
            zs: Vec::with_capacity(padded_len),
            dist: Vec::with_capacity(padded_len),
            ids: Vec::with_capacity(padded_len),
            leaf_range: Vec::with_capacity(first_leaf + 1),
            first_leaf,
            node_lo: vec![[f32::INFINITY; 3]; 2 * first_leaf],
            node_hi: vec![[f32::NEG_INFINITY; 3]; 2 * first_leaf],
            node_max: vec![f32::INFINITY; 2 * first_leaf],
        };
        for (leaf, w) in bounds.windows(2).enumerate() {
            tree.leaf_range.push(tree.xs.len());
            let leaf_records = &records[w[0]..w[1]];
            let padded = leaf_records.len().div_ceil(LANES) * LANES;
            for k in 0..padded {
                let real = leaf_records.get(k);
                let r = real.or(leaf_records.first()).copied().unwrap_or(PointRecord { p: [0.0; 3], id: u32::MAX });
                tree.xs.push(r.p[0]);
                tree.ys.push(r.p[1]);
                tree.zs.push(r.p[2]);
                tree.dist.push(if real.is_some() { f32::INFINITY } else { f32::NEG_INFINITY });
                tree.ids.push(if real.is_some() { r.id } else { u32::MAX });
            }
            let (lo, hi) = bounding_box(leaf_records);
            tree.node_lo[first_leaf + leaf] = lo;
            tree.node_hi[first_leaf + leaf] = hi;
            if leaf_records.is_empty() {
                tree.node_max[first_leaf + leaf] = f32::NEG_INFINITY;
            }
        }
        tree.leaf_range.push(tree.xs.len());
        for node in (1..first_leaf).rev() {
            for a in 0..3 {
                tree.node_lo[node][a] = tree.node_lo[2 * node][a].min(tree.node_lo[2 * node + 1][a]);
                tree.node_hi[node][a] = tree.node_hi[2 * node][a].max(tree.node_hi[2 * node + 1][a]);
            }
            tree.node_max[node] = tree.node_max[2 * node].max(tree.node_max[2 * node + 1]);
        }
        tree
    }

    /// Folds the pick `p` into the distances of `node`'s subtree.
    ///
    /// Skip rule: the subtree is untouched when its largest distance is <= the squared distance
    /// from `p` to its bounding box. Exact (not approximate): rounding is monotone, so every
    /// point's computed squared distance to `p` is >= the box's, computed the same way.
    #[inline(always)]
    fn update(&mut self, node: usize, p: [f32; 3]) {
        if self.node_max[node] <= box_distance2(p, self.node_lo[node], self.node_hi[node]) {
            return;
        }
        if node >= self.first_leaf {
            let leaf = node - self.first_leaf;
            let range = self.leaf_range[leaf]..self.leaf_range[leaf + 1];
            self.node_max[node] = update_leaf(
                &self.xs[range.clone()],
                &self.ys[range.clone()],
                &self.zs[range.clone()],
                &mut self.dist[range],
                p,
            );
        } else {
            self.update(2 * node, p);
            self.update(2 * node + 1, p);
            self.node_max[node] = self.node_max[2 * node].max(self.node_max[2 * node + 1]);
        }
    }

    /// Lowest point id in `node`'s subtree whose distance equals `best` (u32::MAX if none).
    fn lowest_id_at(&self, node: usize, best: f32) -> u32 {
        if self.node_max[node] != best {
            return u32::MAX;
        }
        if node >= self.first_leaf {
            let leaf = node - self.first_leaf;
            let range = self.leaf_range[leaf]..self.leaf_range[leaf + 1];
            return self.dist[range.clone()]
                .iter()
                .zip(&self.ids[range])
                .filter(|(d, _)| **d == best)
                .map(|(_, id)| *id)
                .min()
                .unwrap_or(u32::MAX);
        }
        self.lowest_id_at(2 * node, best).min(self.lowest_id_at(2 * node + 1, best))
    }
}

/// Squared distance from `p` to the box `[lo, hi]` (0 inside), computed like the point
/// distances in [`update_leaf`].
#[inline(always)]
fn box_distance2(p: [f32; 3], lo: [f32; 3], hi: [f32; 3]) -> f32 {
    let gap = |a: usize| {
        if p[a] < lo[a] {
            lo[a] - p[a]
        } else if p[a] > hi[a] {
            p[a] - hi[a]
        } else {
            0.0
        }
    };
    let (gx, gy, gz) = (gap(0), gap(1), gap(2));
    gx * gx + gy * gy + gz * gz
}

/// `dist[i] = min(dist[i], |x_i - p|^2)` over one leaf (length a multiple of [`LANES`]);
/// returns the new largest `dist`. Written lane-wise so it compiles to vector min/max.
#[inline(always)]
fn update_leaf(xs: &[f32], ys: &[f32], zs: &[f32], dist: &mut [f32], p: [f32; 3]) -> f32 {
    let mut lane_max = [f32::NEG_INFINITY; LANES];
    for (((x, y), z), d) in
        xs.chunks_exact(LANES).zip(ys.chunks_exact(LANES)).zip(zs.chunks_exact(LANES)).zip(dist.chunks_exact_mut(LANES))
    {
        for l in 0..LANES {
            let dx = x[l] - p[0];
            let dy = y[l] - p[1];
            let dz = z[l] - p[2];
            let candidate = dx * dx + dy * dy + dz * dz;
            let nearest = if candidate < d[l] { candidate } else { d[l] };
            d[l] = nearest;
            lane_max[l] = if nearest > lane_max[l] { nearest } else { lane_max[l] };
        }
    }
    lane_max.iter().fold(f32::NEG_INFINITY, |m, &v| if v > m { v } else { m })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The textbook O(N n) loop, lowest index on ties.
    fn reference_fps(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
        let mut dist = vec![f32::INFINITY; points.len()];
        let mut picks = vec![first];
        let mut last = first;
        while picks.len() < n {
            let p = points[last];
            let mut best = (f32::NEG_INFINITY, 0);
            for (i, q) in points.iter().enumerate() {
                let (dx, dy, dz) = (q[0] - p[0], q[1] - p[1], q[2] - p[2]);
                let d = dx * dx + dy * dy + dz * dz;
                if d < dist[i] {
                    dist[i] = d;
                }
                if dist[i] > best.0 {
                    best = (dist[i], i);
                }
            }
            last = best.1;
            picks.push(last);
        }
        picks
    }

    fn random_cloud(rng: &mut ChaCha8Rng, n: usize) -> Vec<[f32; 3]> {
        (0..n).map(|_| std::array::from_fn(|_| rng.random_range(-1.0f32..1.0))).collect()
    }

    #[test]
    fn fps_matches_the_reference_loop() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for (size, n) in [(2usize, 1usize), (3, 2), (17, 9), (100, 50), (1000, 300), (5000, 1024), (4096, 1024)] {
            let cloud = random_cloud(&mut rng, size);
            let first = rng.random_range(0..size);
            assert_eq!(
                farthest_point_sample(&cloud, n, first).unwrap(),
                reference_fps(&cloud, n, first),
                "{size} -> {n}"
            );
        }
        // Clustered and anisotropic clouds.
        let mut cloud: Vec<[f32; 3]> = (0..3000)
            .map(|i| {
                let c = (i % 5) as f32 * 0.4 - 0.8;
                [
                    c + rng.random_range(-0.01f32..0.01),
                    rng.random_range(-1.0f32..1.0) * 0.01,
                    rng.random_range(0.0f32..0.05),
                ]
            })
            .collect();
        cloud.extend(random_cloud(&mut rng, 200));
        assert_eq!(farthest_point_sample(&cloud, 700, 5).unwrap(), reference_fps(&cloud, 700, 5));
    }

    #[test]
    fn fps_ties_and_duplicates_pick_the_lowest_index() {
        // A coarse integer grid, every point three times: distances tie all the time.
        let mut cloud = Vec::new();
        for _ in 0..3 {
            for x in 0..6 {
                for y in 0..5 {
                    for z in 0..4 {
                        cloud.push([x as f32, y as f32, z as f32]);
                    }
                }
            }
        }
        for n in [10, 120, 200, 359] {
            assert_eq!(farthest_point_sample(&cloud, n, 7).unwrap(), reference_fps(&cloud, n, 7), "n = {n}");
        }
        let same = vec![[0.5f32; 3]; 50];
        assert_eq!(farthest_point_sample(&same, 4, 3).unwrap(), vec![3, 0, 0, 0]);
    }

    #[test]
    fn fps_with_a_parallel_build_matches_the_reference() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let cloud = random_cloud(&mut rng, 4 * PARALLEL_BUILD_MIN_POINTS + 999);
        assert_eq!(farthest_point_sample(&cloud, 64, 42).unwrap(), reference_fps(&cloud, 64, 42));
    }

    #[test]
    fn fps_edge_cases() {
        let cloud = [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]];
        assert_eq!(farthest_point_sample(&cloud, 3, 1).unwrap(), vec![0, 1, 2], "n >= len gives all indices");
        assert_eq!(farthest_point_sample(&cloud, 10, 0).unwrap(), vec![0, 1, 2]);
        assert_eq!(farthest_point_sample(&cloud, 2, 1).unwrap(), vec![1, 2]);
        assert!(farthest_point_sample(&[], 4, 0).unwrap().is_empty());
        assert!(farthest_point_sample(&cloud, 2, 3).is_err());
        assert!(farthest_point_sample(&[[0.0, f32::NAN, 0.0], [1.0; 3], [2.0; 3]], 2, 0).is_err());
    }
}
