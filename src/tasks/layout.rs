//! Random placement of objects on the table (rejection sampling, seeded).
use std::ops::Range;

use nalgebra::Vector2;
use rand::Rng;
use rand::rngs::StdRng;

/// `count` points uniform in `x` x `y` (world, m), each accepted when `accept(placed, candidate)`.
pub fn scatter(
    rng: &mut StdRng,
    count: usize,
    x: Range<f64>,
    y: Range<f64>,
    accept: impl Fn(&[Vector2<f64>], &Vector2<f64>) -> bool,
) -> Vec<Vector2<f64>> {
    let mut spots: Vec<Vector2<f64>> = Vec::with_capacity(count);
    while spots.len() < count {
        let p = Vector2::new(rng.random_range(x.clone()), rng.random_range(y.clone()));
        if accept(&spots, &p) {
            spots.push(p);
        }
    }
    spots
}

/// Accepts candidates at least `gap` metres from every placed point.
pub fn apart(gap: f64) -> impl Fn(&[Vector2<f64>], &Vector2<f64>) -> bool {
    move |placed, p| placed.iter().all(|q| (p - q).norm() > gap)
}
