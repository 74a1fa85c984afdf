//! The training RNG: the randomness of step `s` is a pure function of `(seed, s)`, so a run
//! resumed from a checkpoint draws exactly what the uninterrupted run would have.
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::policy::checkpoint::format::fnv1a64;

/// The RNG for training step `step` of the run seeded with `seed`: ChaCha8
/// keyed by the seed, on stream `step`. Pure in `(seed, step)`: a resumed run
/// draws exactly the numbers of the uninterrupted one. Draw from it in a fixed
/// order within the step (e.g. batch indices, then `a0`, then `t`).
pub fn step_rng(seed: u64, step: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(step);
    rng
}

/// Like [`step_rng`] but with an independent key per `purpose` (e.g.
/// `"noise"`, `"augment"`), so adding draws for one purpose does not shift
/// another's.
pub fn step_rng_for(seed: u64, step: u64, purpose: &str) -> ChaCha8Rng {
    let key = seed ^ fnv1a64(purpose.as_bytes()).rotate_left(17);
    step_rng(key, step)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    #[test]
    fn step_rng_is_pure_in_seed_and_step() {
        let draw = |mut r: ChaCha8Rng| -> Vec<u32> { (0..8).map(|_| r.random()).collect() };
        assert_eq!(draw(step_rng(1, 5)), draw(step_rng(1, 5)));
        assert_ne!(draw(step_rng(1, 5)), draw(step_rng(1, 6)));
        assert_ne!(draw(step_rng(1, 5)), draw(step_rng(2, 5)));
        assert_ne!(draw(step_rng_for(1, 5, "noise")), draw(step_rng_for(1, 5, "augment")));
        assert_eq!(draw(step_rng_for(1, 5, "noise")), draw(step_rng_for(1, 5, "noise")));
    }
}
