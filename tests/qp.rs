//! The patched OSQP (third_party/osqp): `Problem::update_P_A` updates both matrices in one
//! call. It must solve the same problem as `update_P` then `update_A`, and refuse bad data with
//! an error instead of a panic (the OSC calls it in every control tick).
use osqp::{CscMatrix, Problem, Settings, Status};

fn csc(nrows: usize, ncols: usize, indptr: &[usize], indices: &[usize], data: &[f64]) -> CscMatrix<'static> {
    CscMatrix {
        nrows,
        ncols,
        indptr: indptr.to_vec().into(),
        indices: indices.to_vec().into(),
        data: data.to_vec().into(),
    }
}

/// A 3-variable QP's matrices: a dense upper-triangular P, by columns (0,0) (0,1) (1,1) (0,2)
/// (1,2) (2,2), and a dense 2 x 3 A (explicit patterns).
fn problem(p: &[f64; 6], a: &[f64; 6]) -> (CscMatrix<'static>, CscMatrix<'static>) {
    (csc(3, 3, &[0, 1, 3, 6], &[0, 0, 1, 0, 1, 2], p), csc(2, 3, &[0, 2, 4, 6], &[0, 1, 0, 1, 0, 1], a))
}

fn settings() -> Settings {
    Settings::default().verbose(false).polishing(false).eps_abs(1e-10).eps_rel(1e-10).max_iter(100_000)
}

fn solution(problem: &mut Problem) -> Vec<f64> {
    match problem.solve() {
        Status::Solved(s) => s.x().to_vec(),
        other => panic!("the QP did not solve: {other:?}"),
    }
}

#[test]
fn update_p_a_solves_what_separate_updates_solve() {
    let q = [1.0, -2.0, 0.5];
    let (l, u) = ([-1.0, -0.3], [1.0, 0.4]);
    let (p0, a0) = problem(&[2.0, 0.1, 1.5, 0.0, 0.2, 1.0], &[1.0, 0.0, 1.0, 1.0, 0.0, 1.0]);
    // The new data: another P and A of the same patterns, with the second row active.
    let (p1, a1) = problem(&[4.0, -0.5, 3.0, 0.3, 0.0, 2.5], &[0.7, 0.2, -0.4, 1.1, 0.9, 0.6]);
    let mut together = Problem::new(&p0, &q, &a0, &l, &u, &settings()).unwrap();
    let mut apart = Problem::new(&p0, &q, &a0, &l, &u, &settings()).unwrap();
    let mut fresh = Problem::new(&p1, &q, &a1, &l, &u, &settings()).unwrap();
    together.update_P_A(&p1, &a1).unwrap();
    apart.update_P(&p1);
    apart.update_A(&a1);
    let (x_together, x_apart, x_fresh) = (solution(&mut together), solution(&mut apart), solution(&mut fresh));
    for i in 0..3 {
        assert!((x_together[i] - x_apart[i]).abs() < 1e-7, "{x_together:?} against {x_apart:?}");
        assert!((x_together[i] - x_fresh[i]).abs() < 1e-7, "{x_together:?} against {x_fresh:?}");
    }
    // The update moved the solution (a test that P and A were taken at all).
    let x_old = solution(&mut Problem::new(&p0, &q, &a0, &l, &u, &settings()).unwrap());
    assert!((0..3).any(|i| (x_old[i] - x_together[i]).abs() > 1e-3), "{x_old:?} and {x_together:?}");
}

#[test]
fn update_p_a_refuses_bad_data_without_panicking() {
    let q = [1.0, -2.0, 0.5];
    let (l, u) = ([-1.0, -0.3], [1.0, 0.4]);
    let (p0, a0) = problem(&[2.0, 0.1, 1.5, 0.0, 0.2, 1.0], &[1.0, 0.0, 1.0, 1.0, 0.0, 1.0]);
    let mut qp = Problem::new(&p0, &q, &a0, &l, &u, &settings()).unwrap();
    // More values than P has entries: OSQP refuses the update.
    let too_long = csc(3, 3, &[0, 1, 3, 7], &[0, 0, 1, 0, 1, 2, 2], &[1.0; 7]);
    let refused = qp.update_P_A(&too_long, &a0).unwrap_err();
    assert_ne!(refused.code, 0);
    assert!(refused.to_string().contains("exit code"), "{refused}");
    // A good update afterwards solves the problem again.
    qp.update_P_A(&p0, &a0).unwrap();
    let x = solution(&mut qp);
    assert!(x.iter().all(|v| v.is_finite()));
}
