//! The patched candle backprop (`third_party/README.md`: the first gradient reaching a tensor is
//! stored instead of added into zeros): gradients with fan-in, a subtraction first, a broadcast
//! and a strided first contribution equal their analytic values, stored contiguous.
use candle_core::{DType, Device, Tensor, Var};

type TestResult = Result<(), Box<dyn std::error::Error>>;

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

fn assert_close(got: &Tensor, want: &[f32], what: &str) {
    let got = values(got);
    assert_eq!(got.len(), want.len(), "{what}");
    for (g, w) in got.iter().zip(want) {
        assert!((g - w).abs() <= 1e-5 * w.abs().max(1.0), "{what}: {got:?} against {want:?}");
    }
}

#[test]
fn fan_in_sums_every_contribution() -> TestResult {
    let xs = [0.5f32, -1.0, 2.0, 0.25, -0.75, 1.5];
    let x = Var::from_tensor(&Tensor::new(&xs, &Device::Cpu)?.reshape((2, 3))?)?;
    // x reaches the sum four times: x*x (twice), + x, - exp(x)
    let y = ((x.as_tensor() * x.as_tensor())? + x.as_tensor())?.sub(&x.as_tensor().exp()?)?;
    let grads = y.sum_all()?.backward()?;
    let g = grads.get(&x).expect("x has a gradient");
    let want: Vec<f32> = xs.iter().map(|v| 2.0 * v + 1.0 - v.exp()).collect();
    assert_close(g, &want, "d/dx (x^2 + x - e^x)");
    assert_eq!(g.dims(), &[2, 3]);
    Ok(())
}

#[test]
fn a_subtraction_first_stores_the_negated_gradient() -> TestResult {
    let x = Var::zeros((2, 3), DType::F32, &Device::Cpu)?;
    let b = Tensor::ones((2, 3), DType::F32, &Device::Cpu)?;
    // only the right-hand side of a subtraction: -1
    let grads = b.sub(x.as_tensor())?.sum_all()?.backward()?;
    assert_close(grads.get(&x).unwrap(), &[-1.0; 6], "d/dx (b - x)");
    // a subtraction first, then an addition of 3x: -1 + 3
    let y = (b.sub(x.as_tensor())? + (x.as_tensor() * 3.0)?)?;
    let grads = y.sum_all()?.backward()?;
    assert_close(grads.get(&x).unwrap(), &[2.0; 6], "d/dx (b - x + 3x)");
    // a division's right-hand side (the other subtracting rule): d/dx (6 / x) = -6 / x^2
    let x = Var::from_tensor(&Tensor::new(&[1f32, 2.0, 3.0], &Device::Cpu)?)?;
    let six = Tensor::new(&[6f32, 6.0, 6.0], &Device::Cpu)?;
    let grads = six.div(x.as_tensor())?.sum_all()?.backward()?;
    assert_close(grads.get(&x).unwrap(), &[-6.0, -1.5, -6.0 / 9.0], "d/dx (6 / x)");
    Ok(())
}

#[test]
fn broadcast_and_strided_first_contributions_are_stored_contiguous() -> TestResult {
    // a bias broadcast over two rows: each element's gradient is summed over the rows
    let w = Var::from_tensor(&Tensor::new(&[1f32, 2.0, 3.0], &Device::Cpu)?)?;
    let a = Tensor::new(&[[1f32, 1.0, 1.0], [2.0, 2.0, 2.0]], &Device::Cpu)?;
    let grads = (a.broadcast_mul(w.as_tensor())?).sum_all()?.backward()?;
    assert_close(grads.get(&w).unwrap(), &[3.0, 3.0, 3.0], "d/dw sum(a * w)");
    // the first (and only) contribution to x comes through a transpose: a strided view
    let x = Var::from_tensor(&Tensor::new(&[[1f32, 2.0, 3.0], [4.0, 5.0, 6.0]], &Device::Cpu)?)?;
    let k = Tensor::new(&[[1f32, 2.0], [3.0, 4.0], [5.0, 6.0]], &Device::Cpu)?;
    let grads = (x.as_tensor().t()? * &k)?.sum_all()?.backward()?;
    let g = grads.get(&x).unwrap();
    assert_close(g, &values(&k.t()?.contiguous()?), "d/dx sum(x^T * k) = k^T");
    assert!(g.is_contiguous(), "a stored first gradient is contiguous");
    Ok(())
}
