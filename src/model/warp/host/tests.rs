use super::*;

/// The dense prefilter of `crate::model::stencil`, applied along both axes (with
/// `transpose`, its transpose `Pᵀ`).
fn dense_prefilter(data: &[f64], h: usize, w: usize, transpose: bool) -> Vec<f64> {
    let (ph, pw) = (
        crate::model::stencil::bspline_prefilter(h),
        crate::model::stencil::bspline_prefilter(w),
    );
    let entry = |m: &crate::model::stencil::Matrix, i: usize, k: usize| {
        if transpose { m.get(k, i) } else { m.get(i, k) }
    };
    let mut out = vec![0.0; h * w];
    for i in 0..h {
        for j in 0..w {
            let mut acc = 0.0;
            for k in 0..h {
                for l in 0..w {
                    acc += entry(&ph, i, k) * entry(&pw, j, l) * data[k * w + l];
                }
            }
            out[i * w + j] = acc;
        }
    }
    out
}

fn ramp(n: usize, seed: f64) -> Vec<f64> {
    (0..n)
        .map(|i| (i as f64 * 0.37 + seed).sin() + 0.1 * i as f64 % 3.0)
        .collect()
}

#[test]
fn prefiltering_into_a_new_buffer_equals_prefiltering_in_place() {
    // 3 planes of 11 × 9: line groups that end inside a plane and across planes.
    let (h, w) = (11, 9);
    let source: Vec<f64> = ramp(3 * h * w, 0.4);
    for transpose in [false, true] {
        let mut in_place = source.clone();
        prefilter(&mut in_place, h, w, transpose);
        let mut into = vec![0.0; source.len()];
        prefilter_into(&source, &mut into, h, w, transpose);
        assert_eq!(in_place, into, "transpose {transpose}");
    }
}

/// The prefilters run a task per plane (or image) when there are at least as many as
/// threads, else split rows and column blocks across threads: both orders of work give
/// the same bits, in float32 where reordered arithmetic would show.
#[test]
fn the_prefilters_split_of_work_does_not_change_a_bit() {
    // Two images of 21 or 9 channels, 13 × 10 (line groups and column blocks that end
    // inside a plane). One thread: a task per plane or image. 4 threads: the
    // channels-last images in split rows and columns. 64 threads: the planar passes too.
    let (n, h, w) = (2, 13, 10);
    for c in [21, 9] {
        let f: Vec<f32> = ramp(n * c * h * w, 0.6).iter().map(|&v| v as f32).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a thread pool");
            pool.install(|| {
                let (mut forward, mut adjoint) = (f.clone(), f.clone());
                prefilter(&mut forward, h, w, false);
                prefilter(&mut adjoint, h, w, true);
                let mut into = vec![0.0f32; f.len()];
                prefilter_into(&f, &mut into, h, w, true);
                let mut table = vec![f32::NAN; f.len()];
                prefilter_channels_last(&f, &mut table, (n, c, h, w));
                [forward, adjoint, into, table]
            })
        };
        let whole = run(1);
        for threads in [4, 64] {
            let split = run(threads);
            for (what, (a, b)) in ["P", "Pᵀ", "Pᵀ into", "channels-last P"]
                .iter()
                .zip(whole.iter().zip(&split))
            {
                let same = a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
                assert!(
                    same,
                    "{what}, {c} channels, {threads} threads: not the same bits"
                );
            }
        }
    }
}

#[test]
fn the_line_solve_is_the_dense_prefilter_and_its_transpose_the_adjoint() {
    for (h, w) in [(4, 4), (5, 9), (13, 7), (40, 33)] {
        let f = ramp(2 * h * w, 0.3);
        let mut c = f.clone();
        prefilter(&mut c, h, w, false);
        for p in 0..2 {
            let want = dense_prefilter(&f[p * h * w..(p + 1) * h * w], h, w, false);
            for (a, b) in c[p * h * w..(p + 1) * h * w].iter().zip(&want) {
                assert!((a - b).abs() < 1e-12, "{h}x{w}: {a} vs {b}");
            }
        }
        // ⟨P f, g⟩ = ⟨f, Pᵀ g⟩.
        let g = ramp(2 * h * w, 1.7);
        let mut pt = g.clone();
        prefilter(&mut pt, h, w, true);
        let lhs: f64 = c.iter().zip(&g).map(|(a, b)| a * b).sum();
        let rhs: f64 = f.iter().zip(&pt).map(|(a, b)| a * b).sum();
        assert!(
            (lhs - rhs).abs() < 1e-10 * lhs.abs().max(1.0),
            "{lhs} vs {rhs}"
        );
    }
}

/// For few channels (planar reads) and many (channels-last, with a remainder after the
/// 8-wide lanes of the dot products).
#[test]
fn the_adjoint_and_the_position_gradient_match_the_evaluation() {
    for c in [3, CHANNELS_LAST_FROM + 3] {
        adjoint_and_position_gradient_match(c);
    }
}

/// The evaluation writes every output value (the op hands it uninitialised memory):
/// planar and channels-last, whole tasks and tiles and their remainders, from planar
/// coefficients and from a channels-last table, each output first filled with NaN.
#[test]
fn the_evaluation_writes_every_value() {
    // 2 images of 40 × 31 points: a task of 1024 points and a remainder, tiles of 64
    // and a remainder.
    let (n, h, w) = (2, 40, 31);
    let phi: Vec<f64> = (0..n * 2 * h * w)
        .map(|i| (i as f64 * 0.377).rem_euclid(30.0) - 1.0)
        .collect();
    for c in [3, CHANNELS_LAST_FROM, 13] {
        let d = Dims {
            n,
            c,
            h,
            w,
            ho: h,
            wo: w,
        };
        let coeffs = ramp(n * c * h * w, 0.3);
        let mut out = vec![f64::NAN; n * c * h * w];
        sample(&coeffs, &phi, &mut out, d);
        assert!(out.iter().all(|v| v.is_finite()), "{c} planar channels");
        if !reads_channels_last(c) {
            continue;
        }
        let mut table = vec![0.0; coeffs.len()];
        for b in 0..n {
            let image = b * c * h * w..(b + 1) * c * h * w;
            channels_last_into(&coeffs[image.clone()], c, h * w, &mut table[image]);
        }
        let mut from_table = vec![f64::NAN; out.len()];
        sample_from_table(&table, c, &phi, &mut from_table, d);
        assert_eq!(from_table, out, "{c} channels from a channels-last table");
    }
}

/// The adjoint writes every output value (the op hands it uninitialised memory), on both
/// of its paths: a task per group of planes (many planes), and partial planes added
/// (fewer planes than twice the threads).
#[test]
fn the_adjoint_writes_every_value() {
    let (h, w) = (40, 31);
    for (n, c) in [(1, 1), (1, 3), (2, 11)] {
        let d = Dims {
            n,
            c,
            h,
            w,
            ho: h,
            wo: w,
        };
        let phi: Vec<f64> = (0..n * 2 * h * w)
            .map(|i| (i as f64 * 0.377).rem_euclid(30.0) - 1.0)
            .collect();
        let grad = ramp(n * c * h * w, 0.3);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a thread pool");
            let mut out = vec![f64::NAN; n * c * h * w];
            pool.install(|| sample_adjoint(&grad, &phi, &mut out, d));
            out
        };
        let one = run(1);
        for threads in [2, 8] {
            let many = run(threads);
            for (i, (&x, &y)) in many.iter().zip(&one).enumerate() {
                assert!(
                    (x - y).abs() <= 1e-12 * (1.0 + y.abs()),
                    "{n} × {c} planes, {threads} threads, value {i}: {x} against {y}"
                );
            }
        }
    }
}

/// The channels-last adjoint (many channels) gives the per-group scatter's values bit for
/// bit in float32, for channel counts that are and are not multiples of a register, blocks
/// of channels split over 1, 2 and 5 threads, one and two images, points sampled off the
/// coefficient grid (`H' × W'` ≠ `H × W`), on the mirror's folds and outside the clamp
/// range (the stencils that are not four contiguous columns).
#[test]
fn the_channels_last_adjoint_is_the_grouped_one_bit_for_bit() {
    for (n, c) in [(1, 8), (1, 13), (2, 67), (1, 131)] {
        let d = Dims {
            n,
            c,
            h: 23,
            w: 37,
            ho: 19,
            wo: 41,
        };
        let phi: Vec<f32> = (0..n * 2 * d.points())
            .map(|i| {
                let hi = if (i / d.points()).is_multiple_of(2) {
                    22.0
                } else {
                    36.0
                };
                ((i as f64 * 0.773).rem_euclid(hi + 4.0) - 2.0) as f32
            })
            .collect();
        let grad: Vec<f32> = ramp(n * c * d.points(), 0.7)
            .iter()
            .map(|&v| v as f32)
            .collect();
        let planes = n * c * d.h * d.w;
        let mut want = vec![MaybeUninit::new(f32::NAN); planes];
        sample_adjoint_groups(&grad, &phi, &mut want, d, MAX_GROUP);
        for threads in [1, 2, 5] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a thread pool");
            let mut got = vec![MaybeUninit::new(f32::NAN); planes];
            pool.install(|| sample_adjoint_channels_last(&grad, &phi, &mut got, d));
            for (i, (x, y)) in got.iter().zip(&want).enumerate() {
                // SAFETY: both kernels write every value (NaN would show otherwise).
                let (x, y) = unsafe { (x.assume_init(), y.assume_init()) };
                assert_eq!(
                    x.to_bits(),
                    y.to_bits(),
                    "{n} × {c}, {threads} threads, value {i}: {x} against {y}"
                );
            }
        }
    }
}

/// Two images of `c` channels, 9 × 11 coefficients sampled at 7 × 5 points.
fn small_dims(c: usize) -> Dims {
    Dims {
        n: 2,
        c,
        h: 9,
        w: 11,
        ho: 7,
        wo: 5,
    }
}

/// The channels-last prefilter, and evaluations and position gradients read from its
/// table (whole, or a block of channels of it), give the planar path's values bit for
/// bit, in float32 where reordered arithmetic would show.
#[test]
fn channels_last_coefficients_are_the_planar_ones_bit_for_bit() {
    // Two images of 21 channels (a block of 3 + a block of 18), 13 × 10: line groups
    // that end inside an image, and column blocks of 256 values that end inside a row.
    let (n, c, h, w) = (2, 21, 13, 10);
    let (ho, wo) = (6, 7);
    let f: Vec<f32> = ramp(n * c * h * w, 0.2).iter().map(|&v| v as f32).collect();
    let mut planar = f.clone();
    prefilter(&mut planar, h, w, false);
    // NaN first: the op hands the prefilter uninitialised memory, every value is written.
    let mut table = vec![f32::NAN; f.len()];
    prefilter_channels_last(&f, &mut table, (n, c, h, w));
    for b in 0..n {
        let want = channels_last(&planar[b * c * h * w..(b + 1) * c * h * w], c, h * w);
        assert_eq!(
            &table[b * c * h * w..(b + 1) * c * h * w],
            &want[..],
            "image {b}"
        );
    }
    let phi: Vec<f32> = (0..n * 2 * ho * wo)
        .map(|i| ((i as f64 * 0.731).rem_euclid(14.0) - 1.5) as f32)
        .collect();
    for (start, len) in [(0, c), (3, c - 3), (1, CHANNELS_LAST_FROM)] {
        let d = Dims {
            n,
            c: len,
            h,
            w,
            ho,
            wo,
        };
        // The planar coefficients of the block, contiguous.
        let block: Vec<f32> = (0..n)
            .flat_map(|b| {
                let at = (b * c + start) * h * w;
                planar[at..at + len * h * w].to_vec()
            })
            .collect();
        let (mut want, mut got) = (
            vec![0.0f32; n * len * ho * wo],
            vec![1.0f32; n * len * ho * wo],
        );
        sample(&block, &phi, &mut want, d);
        sample_from_table(&table[start..], c, &phi, &mut got, d);
        assert_eq!(want, got, "evaluation of channels {start}..{}", start + len);
        let grad: Vec<f32> = ramp(want.len(), 0.9).iter().map(|&v| v as f32).collect();
        let (mut want, mut got) = (vec![0.0f32; phi.len()], vec![1.0f32; phi.len()]);
        sample_position_grad(&block, &phi, &grad, &mut want, d);
        position_grad_from_table(&table[start..], c, &phi, &grad, &mut got, d);
        assert_eq!(
            want,
            got,
            "position gradient of channels {start}..{}",
            start + len
        );
    }
}

/// Channels-last evaluation gives each plane what the planar one-channel kernel gives it.
#[test]
fn tiles_go_to_planes_as_the_definition_says() {
    // Whole blocks of 16 and 8 points, channels and points left over, written through the
    // caches and streamed (planes a multiple of 16 apart from a 64-byte line, where float32
    // streams on AVX2, and not), in both precisions.
    fn check<T: SplineReal + std::fmt::Debug>() {
        for (count, c, plane) in [
            (64, 67, 67),
            (64, 67, 64),
            (59, 16, 64),
            (35, 13, 38),
            (24, 8, 32),
            (8, 8, 11),
            (5, 3, 8),
        ] {
            for stream in [false, true] {
                let tile: Vec<T> = (0..count * c).map(|i| T::from_i32(i as i32)).collect();
                let mut buffer = vec![T::from_f64(-1.0); c * plane + 64];
                let line = buffer.as_ptr().align_offset(64);
                let out = &mut buffer[line..line + c * plane];
                // SAFETY: `out` holds `c` planes of `plane ≥ count` values.
                unsafe { tile_to_planes_simd(&tile, c, Shared(out.as_mut_ptr()), plane, stream) };
                for ch in 0..c {
                    for i in 0..plane {
                        let want = if i < count {
                            tile[i * c + ch]
                        } else {
                            T::from_f64(-1.0)
                        };
                        assert_eq!(
                            out[ch * plane + i].to_f64(),
                            want.to_f64(),
                            "{count} × {c}, stream {stream}: ({ch}, {i})"
                        );
                    }
                }
            }
        }
    }
    check::<f32>();
    check::<f64>();
}

/// The blocked transpose is the definition, for channel and pixel counts that are and are
/// not multiples of the block, and more pixels than a task.
#[test]
fn planes_go_channels_last_as_the_definition_says() {
    fn check<T: SplineReal + std::fmt::Debug>() {
        for c in [1, 7, 8, 13, 67] {
            for plane in [5, 8, 1030, 2100] {
                let planar: Vec<T> = (0..c * plane).map(|i| T::from_i32(i as i32)).collect();
                let mut out = vec![T::from_i32(-1); c * plane];
                channels_last_into(&planar, c, plane, &mut out);
                for i in 0..plane {
                    for ch in 0..c {
                        assert_eq!(out[i * c + ch], planar[ch * plane + i], "{c} × {plane}");
                    }
                }
            }
        }
    }
    check::<f32>();
    check::<f64>();
}

#[test]
fn many_channels_evaluate_as_each_plane_alone() {
    // Channel counts that take each run width of the evaluation (8, 4, 2 and 1
    // registers) and a remainder.
    for c in [CHANNELS_LAST_FROM + 5, 30, 45, 67] {
        evaluate_as_each_plane_alone(c);
    }
}

fn evaluate_as_each_plane_alone(c: usize) {
    let d = small_dims(c);
    let coeffs = ramp(d.n * c * d.h * d.w, 0.4);
    let phi: Vec<f64> = (0..d.n * 2 * d.ho * d.wo)
        .map(|i| (i as f64 * 0.731).rem_euclid(12.0) - 1.0)
        .collect();
    let mut all = vec![0.0; d.n * c * d.ho * d.wo];
    sample(&coeffs, &phi, &mut all, d);
    let one = Dims { n: 1, c: 1, ..d };
    let (plane, points) = (d.h * d.w, d.ho * d.wo);
    for b in 0..d.n {
        let phi_b = &phi[b * 2 * points..(b + 1) * 2 * points];
        for ch in 0..c {
            let at = b * c + ch;
            let mut alone = vec![0.0; points];
            sample(
                &coeffs[at * plane..(at + 1) * plane],
                phi_b,
                &mut alone,
                one,
            );
            for (x, y) in all[at * points..(at + 1) * points].iter().zip(&alone) {
                assert!((x - y).abs() < 1e-13, "image {b}, channel {ch}: {x} vs {y}");
            }
        }
    }
}

fn adjoint_and_position_gradient_match(c: usize) {
    let d = small_dims(c);
    let coeffs = ramp(d.n * d.c * d.h * d.w, 0.1);
    // Points inside and outside the clamp range, and on grid lines.
    let phi: Vec<f64> = (0..d.n * 2 * d.ho * d.wo)
        .map(|i| {
            let axis = (i / (d.ho * d.wo)) % 2;
            let hi = if axis == 0 { 8.0 } else { 10.0 };
            (i as f64 * 1.618).rem_euclid(hi + 3.0) - 1.5 + if i % 7 == 0 { 0.0 } else { 0.25 }
        })
        .collect();
    let g = ramp(d.n * d.c * d.ho * d.wo, 2.2);
    let mut t = vec![0.0; g.len()];
    sample(&coeffs, &phi, &mut t, d);
    let mut adj = vec![0.0; coeffs.len()];
    sample_adjoint(&g, &phi, &mut adj, d);
    let lhs: f64 = t.iter().zip(&g).map(|(a, b)| a * b).sum();
    let rhs: f64 = coeffs.iter().zip(&adj).map(|(a, b)| a * b).sum();
    assert!((lhs - rhs).abs() < 1e-10 * lhs.abs(), "{lhs} vs {rhs}");

    let mut grad = vec![0.0; phi.len()];
    sample_position_grad(&coeffs, &phi, &g, &mut grad, d);
    let value = |phi: &[f64]| {
        let mut t = vec![0.0; g.len()];
        sample(&coeffs, phi, &mut t, d);
        t.iter().zip(&g).map(|(a, b)| a * b).sum::<f64>()
    };
    let h = 1e-6;
    for i in 0..phi.len() {
        let frac = phi[i] - phi[i].floor();
        let axis_hi = if (i / (d.ho * d.wo)).is_multiple_of(2) {
            8.0
        } else {
            10.0
        };
        if frac.min(1.0 - frac) < 1e-3 || (phi[i] + h > axis_hi && phi[i] - h < axis_hi) {
            continue; // a kink of the clamp or of a weight's branch
        }
        let (mut up, mut down) = (phi.clone(), phi.clone());
        up[i] += h;
        down[i] -= h;
        let fd = (value(&up) - value(&down)) / (2.0 * h);
        assert!(
            (fd - grad[i]).abs() < 1e-6 * (1.0 + fd.abs()),
            "φ[{i}]: {fd} vs {}",
            grad[i]
        );
    }
}

#[test]
fn the_adjoint_splits_few_planes_without_changing_the_sum() {
    let d = Dims {
        n: 1,
        c: 1,
        h: 64,
        w: 64,
        ho: 64,
        wo: 64,
    };
    let phi: Vec<f64> = (0..2 * 64 * 64)
        .map(|i| {
            let (axis, p) = (i / 4096, i % 4096);
            let v = if axis == 0 { p / 64 } else { p % 64 } as f64;
            v + 0.3 * ((p as f64) * 0.01).sin()
        })
        .collect();
    let g = ramp(4096, 0.5);
    let mut out = vec![0.0; 4096];
    sample_adjoint(&g, &phi, &mut out, d);
    // Against a plain sequential scatter.
    let mut want = vec![0.0; 4096];
    for (p, rows, cols) in Points::new(&phi, &d, 0, 0..4096) {
        let (offset, weight) = stencil::<f64>(&rows, &cols, 64);
        for k in 0..16 {
            want[offset[k]] += weight[k] * g[p];
        }
    }
    for (a, b) in out.iter().zip(&want) {
        assert!((a - b).abs() < 1e-12);
    }
}

/// A bright pixel in a long run of zeros (a ReLU feature's usual plane): the recurrences'
/// geometric tails would reach subnormal numbers 60-odd samples away; flushed, no
/// coefficient is subnormal, every one stays within float32 rounding of the float64
/// prefilter's (whose tails do pass through float32's subnormal range), and the planar and
/// channels-last prefilters still agree bit for bit.
#[test]
fn the_prefilter_leaves_no_subnormal_coefficient() {
    let (h, w) = (3, 160);
    let mut f = vec![0.0f64; h * w];
    f[w + 2] = 1.0;
    let mut want = f.clone();
    prefilter(&mut want, h, w, false);
    assert!(
        want.iter()
            .any(|v| *v != 0.0 && v.abs() < f64::from(f32::MIN_POSITIVE)),
        "the case must reach float32's subnormal range unflushed"
    );
    let f32s: Vec<f32> = f.iter().map(|&v| v as f32).collect();
    let mut planar = f32s.clone();
    prefilter(&mut planar, h, w, false);
    let mut table = vec![f32::NAN; f32s.len()];
    prefilter_channels_last(&f32s, &mut table, (1, 1, h, w));
    assert_eq!(planar, table);
    for (i, (&got, &want)) in planar.iter().zip(&want).enumerate() {
        assert!(got == 0.0 || got.is_normal(), "coefficient {i}: {got:e}");
        assert!(
            (f64::from(got) - want).abs() <= 1e-6,
            "coefficient {i}: {got:e} against {want:e}"
        );
    }
}

/// The row solves of a whole group of lines run with the lines as vector lanes (8 × 8
/// transposes in and out, a tail of samples past the last whole block): the same bits as
/// the lines solved one value at a time, in either precision, with values small enough to
/// be flushed on the way.
#[test]
fn lines_solved_as_lanes_are_the_interleaved_solve_bit_for_bit() {
    fn check<T: SplineReal + std::fmt::Debug>() {
        for n in [8, 9, 16, 45, 64, 257] {
            for transpose in [false, true] {
                let factors = prefilter::Tridiagonal::mirrored(n, transpose).cast::<T>();
                // A ramp with runs of tiny values and exact zeros (the flush's cases).
                let group: Vec<T> = ramp(LINES_TOGETHER * n, 0.8)
                    .iter()
                    .enumerate()
                    .map(|(i, &v)| match i % 29 {
                        0..=4 => T::from_f64(v * 1e-40),
                        5..=7 => T::from_f64(0.0),
                        _ => T::from_f64(v),
                    })
                    .collect();
                let mut want = group.clone();
                for lines in want.chunks_mut(8 * n) {
                    prefilter::solve_lines_interleaved(lines, n, &factors);
                }
                let mut got = group.clone();
                // A stale, longer scratch from an earlier group must not matter.
                let mut lanes = vec![[T::from_f64(f64::NAN); LINES_TOGETHER]; n + 3];
                prefilter::solve_lines_simd(&mut got, n, &factors, &mut lanes);
                let same = want
                    .iter()
                    .zip(&got)
                    .all(|(a, b)| a.to_f64().to_bits() == b.to_f64().to_bits());
                assert!(same, "n = {n}, transpose {transpose}: not the same bits");
            }
        }
    }
    check::<f32>();
    check::<f64>();
}

/// Planes tall enough for whole groups of lines as lanes (and a last group that is not):
/// the planar prefilter and the channels-last one still agree bit for bit, forwards, and
/// the planar adjoint is the dense prefilter's transpose.
#[test]
fn tall_planes_prefilter_the_same_bits_planar_and_channels_last() {
    for (c, h, w) in [(1, 70, 45), (3, 64, 8), (2, 33, 5), (5, 40, 33)] {
        let f: Vec<f32> = ramp(c * h * w, 0.5).iter().map(|&v| v as f32).collect();
        let mut planar = f.clone();
        prefilter(&mut planar, h, w, false);
        let mut table = vec![f32::NAN; f.len()];
        prefilter_channels_last(&f, &mut table, (1, c, h, w));
        assert_eq!(channels_last(&planar, c, h * w), table, "{c} × {h} × {w}");
        let g = ramp(c * h * w, 1.1);
        let mut pt = g.clone();
        prefilter(&mut pt, h, w, true);
        for p in 0..c {
            let at = p * h * w..(p + 1) * h * w;
            let want = dense_prefilter(&g[at.clone()], h, w, true);
            for (a, b) in pt[at].iter().zip(&want) {
                assert!((a - b).abs() < 1e-12, "{c} × {h} × {w}: {a} vs {b}");
            }
        }
    }
}
