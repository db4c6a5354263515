//! CubeCL kernels of the spline op for the wgpu backend (and any CubeCL runtime): the same
//! maths as [`super::host`], one unit per sample point (channels inner) for the evaluation
//! and its position gradient, atomic adds for the adjoint scatter (one unit per plane where
//! the device has no float atomics), and one unit per line for the prefilter's tridiagonal
//! solves.

use burn::backend::Cube;
use burn::backend::cubecl::{dtype_to_elem_type, dtype_to_storage_type};
use burn::backend::ops::FloatTensorOps;
use burn::tensor::{DType, TensorData};
use burn_cubecl::cubecl::features::AtomicUsage;
use burn_cubecl::cubecl::ir::Type;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::{CubeCount, CubeDim, calculate_cube_count_elemwise};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_dtype;
use burn_cubecl::tensor::CubeTensor;

use super::op::SplineOps;

/// Whole-sample mirror (SPEC §0) of an index in `[−1, n + 1]`.
#[cube]
fn mirror(i: i32, last: i32) -> usize {
    let mut j = i;
    if j < 0 {
        j = -j;
    }
    if j > last {
        j = 2 * last - j;
    }
    j as usize
}

/// The cubic B-spline weights `β(t+1), β(t), β(t−1), β(t−2)`.
#[cube]
fn weights<F: Float>(t: F) -> (F, F, F, F) {
    let s = F::new(1.0) - t;
    let (t2, s2) = (t * t, s * s);
    (
        s2 * s / F::new(6.0),
        F::new(0.5) * t2 * t - t2 + F::new(2.0 / 3.0),
        F::new(0.5) * s2 * s - s2 + F::new(2.0 / 3.0),
        t2 * t / F::new(6.0),
    )
}

/// Their derivatives `β'`.
#[cube]
fn slopes<F: Float>(t: F) -> (F, F, F, F) {
    let s = F::new(1.0) - t;
    let (t2, s2) = (t * t, s * s);
    (
        F::new(-0.5) * s2,
        F::new(1.5) * t2 - F::new(2.0) * t,
        F::new(2.0) * s - F::new(1.5) * s2,
        F::new(0.5) * t2,
    )
}

/// The clamped position, its floor and fractional part along one axis of `n` samples.
#[cube]
fn locate<F: Float>(p: F, n: u32) -> (i32, F, bool) {
    let hi = F::cast_from(n - 1);
    let inside = p >= F::new(0.0) && p <= hi;
    let q = clamp(p, F::new(0.0), hi);
    let floor = q.floor();
    (i32::cast_from(floor), q - floor, inside)
}

#[cube]
fn pick<F: Float>(w: (F, F, F, F), a: u32) -> F {
    let mut v = w.0;
    if a == 1 {
        v = w.1;
    } else if a == 2 {
        v = w.2;
    } else if a == 3 {
        v = w.3;
    }
    v
}

#[cube(launch)]
fn sample_kernel<F: Float>(
    coeffs: &Tensor<F>,  // [N, C, H, W]
    phi: &Tensor<F>,     // [N, 2, H', W']
    out: &mut Tensor<F>, // [N, C, H', W']
    #[define(F)] _dtype: ElemType,
) {
    let points = phi.shape(2) * phi.shape(3);
    let batch = phi.shape(0);
    if ABSOLUTE_POS >= batch * points {
        terminate!();
    }
    let n = ABSOLUTE_POS / points;
    let p = ABSOLUTE_POS % points;
    let (channels, h, w) = (coeffs.shape(1), coeffs.shape(2), coeffs.shape(3));
    let at = n * 2 * points + p;
    let (r, tr, _i0) = locate::<F>(phi[at], h as u32);
    let (c, tc, _i1) = locate::<F>(phi[at + points], w as u32);
    let (wr, wc) = (weights::<F>(tr), weights::<F>(tc));
    let (lr, lc) = (h as i32 - 1, w as i32 - 1);
    for ch in 0..channels {
        let base = (n * channels + ch) * h * w;
        let mut acc = F::new(0.0);
        #[unroll]
        for a in 0..4u32 {
            let row = mirror(r + a as i32 - 1, lr);
            let wa = pick::<F>(wr, a);
            #[unroll]
            for b in 0..4u32 {
                let col = mirror(c + b as i32 - 1, lc);
                acc += wa * pick::<F>(wc, b) * coeffs[base + row * w + col];
            }
        }
        out[(n * channels + ch) * points + p] = acc;
    }
}

#[cube(launch)]
fn position_grad_kernel<F: Float>(
    coeffs: &Tensor<F>,  // [N, C, H, W]
    phi: &Tensor<F>,     // [N, 2, H', W']
    grad: &Tensor<F>,    // [N, C, H', W']
    out: &mut Tensor<F>, // [N, 2, H', W']
    #[define(F)] _dtype: ElemType,
) {
    let points = phi.shape(2) * phi.shape(3);
    let batch = phi.shape(0);
    if ABSOLUTE_POS >= batch * points {
        terminate!();
    }
    let n = ABSOLUTE_POS / points;
    let p = ABSOLUTE_POS % points;
    let (channels, h, w) = (coeffs.shape(1), coeffs.shape(2), coeffs.shape(3));
    let at = n * 2 * points + p;
    let (r, tr, inside_r) = locate::<F>(phi[at], h as u32);
    let (c, tc, inside_c) = locate::<F>(phi[at + points], w as u32);
    let (wr, wc) = (weights::<F>(tr), weights::<F>(tc));
    let (sr, sc) = (slopes::<F>(tr), slopes::<F>(tc));
    let (lr, lc) = (h as i32 - 1, w as i32 - 1);
    let mut g0 = F::new(0.0);
    let mut g1 = F::new(0.0);
    for ch in 0..channels {
        let base = (n * channels + ch) * h * w;
        let mut t0 = F::new(0.0);
        let mut t1 = F::new(0.0);
        #[unroll]
        for a in 0..4u32 {
            let row = mirror(r + a as i32 - 1, lr);
            #[unroll]
            for b in 0..4u32 {
                let col = mirror(c + b as i32 - 1, lc);
                let v = coeffs[base + row * w + col];
                t0 += pick::<F>(sr, a) * pick::<F>(wc, b) * v;
                t1 += pick::<F>(wr, a) * pick::<F>(sc, b) * v;
            }
        }
        let g = grad[(n * channels + ch) * points + p];
        g0 += g * t0;
        g1 += g * t1;
    }
    let zero = F::new(0.0);
    out[at] = select(inside_r, g0, zero);
    out[at + points] = select(inside_c, g1, zero);
}

#[cube(launch)]
fn adjoint_atomic_kernel<F: Float>(
    grad: &Tensor<F>,            // [N, C, H', W']
    phi: &Tensor<F>,             // [N, 2, H', W']
    out: &mut Tensor<Atomic<F>>, // [N, C, H, W], zeroed
    #[define(F)] _dtype: ElemType,
) {
    let points = phi.shape(2) * phi.shape(3);
    let batch = phi.shape(0);
    if ABSOLUTE_POS >= batch * points {
        terminate!();
    }
    let n = ABSOLUTE_POS / points;
    let p = ABSOLUTE_POS % points;
    let (channels, h, w) = (out.shape(1), out.shape(2), out.shape(3));
    let at = n * 2 * points + p;
    let (r, tr, _i0) = locate::<F>(phi[at], h as u32);
    let (c, tc, _i1) = locate::<F>(phi[at + points], w as u32);
    let (wr, wc) = (weights::<F>(tr), weights::<F>(tc));
    let (lr, lc) = (h as i32 - 1, w as i32 - 1);
    for ch in 0..channels {
        let base = (n * channels + ch) * h * w;
        let g = grad[(n * channels + ch) * points + p];
        #[unroll]
        for a in 0..4u32 {
            let row = mirror(r + a as i32 - 1, lr);
            #[unroll]
            for b in 0..4u32 {
                let col = mirror(c + b as i32 - 1, lc);
                out[base + row * w + col].fetch_add(pick::<F>(wr, a) * pick::<F>(wc, b) * g);
            }
        }
    }
}

/// One unit per plane, walking its points in order: for devices without float atomics
/// (deterministic, slow).
#[cube(launch)]
fn adjoint_serial_kernel<F: Float>(
    grad: &Tensor<F>,    // [N, C, H', W']
    phi: &Tensor<F>,     // [N, 2, H', W']
    out: &mut Tensor<F>, // [N, C, H, W], zeroed
    #[define(F)] _dtype: ElemType,
) {
    let points = phi.shape(2) * phi.shape(3);
    let (batch, channels, h, w) = (out.shape(0), out.shape(1), out.shape(2), out.shape(3));
    if ABSOLUTE_POS >= batch * channels {
        terminate!();
    }
    let n = ABSOLUTE_POS / channels;
    let base = ABSOLUTE_POS * h * w;
    let (lr, lc) = (h as i32 - 1, w as i32 - 1);
    for p in 0..points {
        let at = n * 2 * points + p;
        let (r, tr, _i0) = locate::<F>(phi[at], h as u32);
        let (c, tc, _i1) = locate::<F>(phi[at + points], w as u32);
        let (wr, wc) = (weights::<F>(tr), weights::<F>(tc));
        let g = grad[ABSOLUTE_POS * points + p];
        #[unroll]
        for a in 0..4u32 {
            let row = mirror(r + a as i32 - 1, lr);
            #[unroll]
            for b in 0..4u32 {
                let col = mirror(c + b as i32 - 1, lc);
                out[base + row * w + col] += pick::<F>(wr, a) * pick::<F>(wc, b) * g;
            }
        }
    }
}

/// The tridiagonal solve of [`super::host`] along lines of `len` samples, `stride` apart,
/// starting at `start(line) = (line / inner) · outer + line % inner`: rows (`stride` 1) or
/// columns (`stride` W) of every plane.
// The kernel scales an indexed element in place as CubeCL expands it: `a[i] = a[i] * x`.
#[allow(clippy::assign_op_pattern)]
#[cube(launch)]
fn solve_lines_kernel<F: Float>(
    data: &mut Tensor<F>,
    lower: &Tensor<F>,
    pivot: &Tensor<F>,
    upper: &Tensor<F>,
    lines: u32,
    len: u32,
    stride: u32,
    inner: u32,
    outer: u32,
    #[define(F)] _dtype: ElemType,
) {
    if ABSOLUTE_POS >= lines as usize {
        terminate!();
    }
    let line = ABSOLUTE_POS as u32;
    let start = ((line / inner) * outer + line % inner) as usize;
    let (len, stride) = (len as usize, stride as usize);
    data[start] = data[start] * pivot[0];
    for i in 1..len {
        let here = start + i * stride;
        data[here] = (data[here] - lower[i] * data[here - stride]) * pivot[i];
    }
    for k in 1..len {
        let i = len - 1 - k;
        let here = start + i * stride;
        data[here] = data[here] - upper[i] * data[here + stride];
    }
}

fn units(client_tensor: &CubeTensor, count: usize) -> (CubeCount, CubeDim) {
    let cube_dim = CubeDim::new(&client_tensor.client, count.max(1));
    let cube_count = calculate_cube_count_elemwise(&client_tensor.client, count.max(1), cube_dim);
    (cube_count, cube_dim)
}

fn dims4(t: &CubeTensor) -> [usize; 4] {
    t.meta.shape().dims()
}

/// The prefilter's tridiagonal factors for lines of `n` samples, beside `like`.
fn factors(n: usize, transpose: bool, like: &CubeTensor) -> [CubeTensor; 3] {
    let t = super::host::factors(n, transpose);
    [t.0, t.1, t.2].map(|v| {
        let len = v.len();
        let data = match like.dtype {
            DType::F64 => TensorData::new(v, [len]),
            _ => TensorData::new(v.iter().map(|&x| x as f32).collect::<Vec<f32>>(), [len]),
        };
        Cube::float_from_data(data, &like.device)
    })
}

impl SplineOps for Cube {
    fn spline_prefilter(x: CubeTensor, transpose: bool) -> CubeTensor {
        let x = into_contiguous(x).copy();
        let [n, c, h, w] = dims4(&x);
        let dtype = dtype_to_storage_type(x.dtype);
        let solve = |len: usize, lines: usize, stride: usize, inner: usize, outer: usize| {
            let [lower, pivot, upper] = factors(len, transpose, &x);
            let (count, dim) = units(&x, lines);
            solve_lines_kernel::launch(
                &x.client,
                count,
                dim,
                x.clone().into_tensor_arg(),
                lower.into_tensor_arg(),
                pivot.into_tensor_arg(),
                upper.into_tensor_arg(),
                lines as u32,
                len as u32,
                stride as u32,
                inner as u32,
                outer as u32,
                dtype,
            );
        };
        // Rows: lines along W, one per (plane, row). Columns: lines along H, one per
        // (plane, column), `W` apart.
        solve(w, n * c * h, 1, 1, w);
        solve(h, n * c * w, w, w, h * w);
        x
    }

    fn spline_sample(coeffs: CubeTensor, phi: CubeTensor) -> CubeTensor {
        let (coeffs, phi) = (into_contiguous(coeffs), into_contiguous(phi));
        let [n, c, _, _] = dims4(&coeffs);
        let [_, _, ho, wo] = dims4(&phi);
        let out = empty_device_dtype(
            coeffs.client.clone(),
            coeffs.device.clone(),
            [n, c, ho, wo].into(),
            coeffs.dtype,
        );
        let (count, dim) = units(&coeffs, n * ho * wo);
        let dtype = dtype_to_storage_type(coeffs.dtype);
        sample_kernel::launch(
            &out.client,
            count,
            dim,
            coeffs.into_tensor_arg(),
            phi.into_tensor_arg(),
            out.clone().into_tensor_arg(),
            dtype,
        );
        out
    }

    fn spline_sample_adjoint(
        grad: CubeTensor,
        phi: CubeTensor,
        height: usize,
        width: usize,
    ) -> CubeTensor {
        let (grad, phi) = (into_contiguous(grad), into_contiguous(phi));
        let [n, c, ho, wo] = dims4(&grad);
        let zeros = TensorData::full_dtype([n, c, height, width], 0.0, grad.dtype);
        let out = Cube::float_from_data(zeros, &grad.device);
        let dtype = dtype_to_storage_type(grad.dtype);
        let atomic = grad
            .client
            .properties()
            .atomic_type_usage(Type::atomic(dtype_to_elem_type(grad.dtype)))
            .contains(AtomicUsage::Add);
        if atomic {
            let (count, dim) = units(&grad, n * ho * wo);
            adjoint_atomic_kernel::launch(
                &out.client,
                count,
                dim,
                grad.into_tensor_arg(),
                phi.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                dtype,
            );
        } else {
            let (count, dim) = units(&grad, n * c);
            adjoint_serial_kernel::launch(
                &out.client,
                count,
                dim,
                grad.into_tensor_arg(),
                phi.into_tensor_arg(),
                out.clone().into_tensor_arg(),
                dtype,
            );
        }
        out
    }

    fn spline_sample_position_grad(
        coeffs: CubeTensor,
        phi: CubeTensor,
        grad: CubeTensor,
    ) -> CubeTensor {
        let (coeffs, phi, grad) = (
            into_contiguous(coeffs),
            into_contiguous(phi),
            into_contiguous(grad),
        );
        let [n, _, ho, wo] = dims4(&phi);
        let out = empty_device_dtype(
            coeffs.client.clone(),
            coeffs.device.clone(),
            [n, 2, ho, wo].into(),
            coeffs.dtype,
        );
        let (count, dim) = units(&coeffs, n * ho * wo);
        let dtype = dtype_to_storage_type(coeffs.dtype);
        position_grad_kernel::launch(
            &out.client,
            count,
            dim,
            coeffs.into_tensor_arg(),
            phi.into_tensor_arg(),
            grad.into_tensor_arg(),
            out.clone().into_tensor_arg(),
            dtype,
        );
        out
    }
}
