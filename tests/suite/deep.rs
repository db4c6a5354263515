//! The deep model end to end on the library: feature vectors per level (SPEC §4), the
//! feature-only sweeps after a prolongation (SPEC §7), outputs = RGB part / η (SPEC §8), and
//! SPEC §10's `A = B` invariant. VGG19 here has deterministic He-scaled weights, so no
//! downloaded or shared file is needed.

use crate::common;

use std::sync::atomic::AtomicBool;

use burn::tensor::{DType, Device, Tensor, TensorData};
use common::{device, reference_backend, values};
use deepmorph::eval::metrics::{LandmarkResiduals, compose};
use deepmorph::features::deep::deep_features;
use deepmorph::features::vgg::architecture::conv_shapes;
use deepmorph::features::vgg::weights::ConvWeights;
use deepmorph::features::vgg::{Vgg19, Vgg19Weights};
use deepmorph::model::alignment::GlobalMap;
use deepmorph::model::energy::landmarks::Landmarks;
use deepmorph::model::feature_model::{DeepConfig, FeatureModel};
use deepmorph::solver::multilevel::{Morph, Multilevel, MultilevelConfig};
use deepmorph::solver::observer::{Initialisation, Observer, Phase, SweepEvent};
use deepmorph::{EnergyParams, Precision};

fn random_vgg(device: &Device) -> Vgg19 {
    let mut next = common::uniform(0x2545_f491_4f6c_dd1d);
    let convs = conv_shapes()
        .iter()
        .enumerate()
        .map(|(i, &[o, c, kh, kw])| {
            let scale = (6.0 / (c * kh * kw) as f64).sqrt();
            ConvWeights {
                source: format!("conv {i}"),
                shape: vec![o, c, kh, kw],
                weight: (0..o * c * kh * kw)
                    .map(|_| (next() * scale) as f32)
                    .collect(),
                bias: (0..o).map(|_| (0.05 + 0.05 * next()) as f32).collect(),
            }
        })
        .collect();
    Vgg19::from_weights(Vgg19Weights { convs }, device).unwrap()
}

/// A smooth colourful `[1, 3, h, w]` image; `shift` moves its pattern.
fn image(h: usize, w: usize, shift: f64, device: &Device) -> Tensor<4> {
    let data: Vec<f64> = (0..3 * h * w)
        .map(|n| {
            let (c, i, j) = (n / (h * w), (n / w) % h, n % w);
            let x = (j as f64 - shift) / w as f64;
            let y = i as f64 / h as f64;
            0.5 + 0.4 * ((3.0 + c as f64) * x + 2.0 * y + c as f64).sin() * (4.0 * y).cos()
        })
        .collect();
    Tensor::from_data(TensorData::new(data, [1, 3, h, w]), (device, DType::F32))
}

#[derive(Default)]
struct Events(Vec<(usize, Phase, usize, f64)>);

impl Observer for Events {
    fn sweep(&mut self, e: &SweepEvent<'_>) {
        assert!(e.energy.is_finite());
        self.0.push((e.level, e.phase, e.sweep, e.energy));
    }
}

fn config(levels: usize, sweeps: usize) -> MultilevelConfig {
    MultilevelConfig {
        steps: 3,
        levels,
        sweeps,
        params: EnergyParams::deep(),
        ..MultilevelConfig::default()
    }
}

#[test]
fn features_are_scaled_to_tau_on_every_level() {
    let device = device(reference_backend(), Precision::F32, false);
    let vgg = random_vgg(&device);
    let (a, b) = (image(32, 48, 0.0, &device), image(32, 48, 3.0, &device));
    let tau = 0.7;
    let deep = deep_features(
        &vgg,
        a,
        b,
        DeepConfig {
            feature_rms: tau,
            ..DeepConfig::default()
        },
    )
    .unwrap();
    for s in 0..5 {
        let (fa, fb) = deep.maps(s).unwrap();
        assert_eq!(fa.dims()[2..], [32 >> s, 48 >> s]);
        let all: Vec<f64> = values(fa).into_iter().chain(values(fb)).collect();
        let rms = (all.iter().map(|v| v * v).sum::<f64>() / all.len() as f64).sqrt();
        assert!((rms - tau).abs() < 1e-5 * tau, "tap {s}: rms {rms}");
        assert!(deep.rms()[s] > 0.0);
        assert_eq!(
            deep.layout(s).unwrap().channels(),
            3 + [64, 128, 256, 512, 512][s]
        );
    }
    let err = deep.layout(5).unwrap_err().to_string();
    assert!(err.contains("levels") && err.contains("at most 5"), "{err}");
    let odd = image(24, 40, 0.0, &device);
    let err = deep_features(&vgg, odd.clone(), odd, DeepConfig::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("multiples of 16"), "{err}");
}

/// A deep morph of `a` into `b` with `pre_sweeps` feature-only sweeps, on the reference
/// backend with a random VGG19.
fn deep_morph(
    a: &Tensor<4>,
    b: &Tensor<4>,
    pre_sweeps: usize,
    config: MultilevelConfig,
    observer: &mut dyn Observer,
) -> Morph {
    let device = a.device();
    let vgg = random_vgg(&device);
    let deep = DeepConfig {
        pre_sweeps,
        ..DeepConfig::default()
    };
    let model = FeatureModel::Deep(deep_features(&vgg, a.clone(), b.clone(), deep).unwrap());
    Multilevel::new(config)
        .unwrap()
        .run_with(
            &device,
            a.clone(),
            b.clone(),
            &model,
            observer,
            &AtomicBool::new(false),
        )
        .unwrap()
}

#[test]
fn deep_morph_runs_feature_sweeps_after_prolongation_and_outputs_rgb() {
    let device = device(reference_backend(), Precision::F32, true);
    let (a, b) = (image(32, 32, 0.0, &device), image(32, 32, 2.0, &device));
    let mut events = Events::default();
    let morph = deep_morph(&a, &b, 3, config(2, 4), &mut events);

    // Level 0: joint sweeps only; level 1: 3 feature-only sweeps, then the joint ones.
    let phases: Vec<(usize, Phase, usize)> = events.0.iter().map(|e| (e.0, e.1, e.2)).collect();
    let mut want: Vec<_> = (0..=4).map(|s| (0, Phase::Joint, s)).collect();
    want.extend((0..=3).map(|s| (1, Phase::Features, s)));
    want.extend((0..=4).map(|s| (1, Phase::Joint, s)));
    assert_eq!(phases, want);
    // Feature-only sweeps fit the re-initialised features to the prolongated φ: E falls.
    let e = |level, phase, sweep| {
        events
            .0
            .iter()
            .find(|x| (x.0, x.1, x.2) == (level, phase, sweep))
            .unwrap()
            .3
    };
    assert!(e(1, Phase::Features, 3) < e(1, Phase::Features, 0));
    assert_eq!(e(1, Phase::Features, 3), e(1, Phase::Joint, 0));

    // 3 + 64 channels at the finest level (relu1_2); the frames are RGB in [0, 1] again.
    assert_eq!(morph.state.f[1].dims(), [1, 67, 32, 32]);
    let images = morph.images();
    assert_eq!(images[0].dims(), [1, 3, 32, 32]);
    let diff = |x: Tensor<4>, y: Tensor<4>| values((x - y).abs().max())[0];
    assert!(diff(images[0].clone(), a) < 1e-5, "u_0 must be A");
    assert!(diff(images[3].clone(), b) < 1e-5, "u_K must be B");
    for u in &images {
        let v = values(u.clone());
        assert!(v.iter().all(|x| x.is_finite() && (-0.5..1.5).contains(x)));
    }
}

#[test]
fn equal_images_give_zero_energy_and_a_constant_deep_path() {
    let device = device(reference_backend(), Precision::F32, true);
    let a = image(32, 32, 0.0, &device);
    let mut events = Events::default();
    deep_morph(&a, &a, 2, config(2, 2), &mut events);
    assert!(events.0.iter().all(|e| e.3.abs() < 1e-9), "{:?}", events.0);
    // On one level the path stays exactly A (on two, the interior RGB channels start from the
    // prolongated coarse images, which differ from A by the resampling error, weighted η²).
    let morph = deep_morph(&a, &a, 2, config(1, 3), &mut ());
    for u in morph.images() {
        assert!(values((u - a.clone()).abs().max())[0] < 1e-5);
    }
    for phi in morph.state.phi {
        assert!(values((phi - morph.grid.identity(1)).abs().max())[0] < 1e-5);
    }
}

/// The feature-space path distance (`deepmorph::eval::perceptual`): zero between equal
/// frames; the module's formula, recomputed here from the network's taps; and a morph
/// that is itself the 8-bit cross-fade measures exactly as its cross-fade baseline.
#[test]
fn feature_space_path_distances() {
    use deepmorph::Grid;
    use deepmorph::eval::perceptual::feature_path;
    use deepmorph::io::images::RgbImage;
    // flex: its convolutions are the fastest of the CPU backends (some 30 network passes).
    let device = device(common::fast_cpu_backend(), Precision::F32, false);
    let vgg = random_vgg(&device);
    let (h, w) = (16, 32);
    let grid = Grid::new(h, w, &device, DType::F32).unwrap();
    let host = |t: Tensor<4>| RgbImage::from_tensor(t).unwrap();
    let shifted: Vec<RgbImage> = [0.0, 3.0, 5.0]
        .iter()
        .map(|&s| host(image(h, w, s, &device)))
        .collect();
    let path = feature_path(&vgg, &grid, &shifted).unwrap();

    // The formula: RMS per tap from both endpoints, mean squared difference over each tap
    // relative to it, averaged over the taps.
    let taps: Vec<Vec<Vec<f64>>> = shifted
        .iter()
        .map(|f| {
            vgg.taps(f.to_tensor(&grid).unwrap())
                .into_iter()
                .map(values)
                .collect()
        })
        .collect();
    let rms: Vec<f64> = (0..5)
        .map(|s| {
            let (a, b) = (&taps[0][s], &taps[2][s]);
            let sum: f64 = a.iter().chain(b).map(|v| v * v).sum();
            (sum / (a.len() + b.len()) as f64).sqrt()
        })
        .collect();
    for k in 1..3 {
        let mean_sq: f64 = (0..5)
            .map(|s| {
                let (u, v) = (&taps[k][s], &taps[k - 1][s]);
                let sq: f64 = u.iter().zip(v).map(|(x, y)| (x - y).powi(2)).sum();
                sq / u.len() as f64 / (rms[s] * rms[s])
            })
            .sum::<f64>()
            / 5.0;
        let (got, want) = (path.morph.adjacent[k - 1], mean_sq.sqrt());
        assert!(
            (got - want).abs() <= 1e-4 * want,
            "step {k}: {got} vs {want}"
        );
    }
    assert!(path.morph.adjacent.iter().all(|d| *d > 0.0));

    let still = feature_path(&vgg, &grid, &[shifted[0].clone(), shifted[0].clone()]).unwrap();
    assert_eq!(still.morph.adjacent, vec![0.0]);

    // A "morph" that is the 8-bit cross-fade of its ends measures as the baseline.
    let byte = |v: &f32| (v * 255.0).round() / 255.0;
    let a: Vec<f32> = shifted[0].data().iter().map(byte).collect();
    let b: Vec<f32> = shifted[2].data().iter().map(byte).collect();
    let fade: Vec<RgbImage> = (0..=2)
        .map(|k| {
            let t = k as f32 / 2.0;
            let data = a
                .iter()
                .zip(&b)
                .map(|(&x, &y)| {
                    ((((1.0 - t) * x + t * y) * 255.0).round().clamp(0.0, 255.0)) / 255.0
                })
                .collect();
            RgbImage::new(h, w, data).unwrap()
        })
        .collect();
    let faded = feature_path(&vgg, &grid, &fade).unwrap();
    assert_eq!(faded.morph, faded.crossfade);
    assert!(feature_path(&vgg, &grid, &shifted[..1]).is_err());
}

/// SPEC §11 in the deep model: an initial alignment and landmarks start the coarsest level
/// from carried feature maps (3 + 128 channels there) and steer the path: the pair is met to
/// within a working pixel, every step taken whole from the start, every energy finite.
#[test]
fn landmarks_and_alignment_steer_a_deep_morph() {
    let device = device(reference_backend(), Precision::F32, true);
    let (a, b) = (image(32, 32, 0.0, &device), image(32, 32, 6.0, &device));
    let vgg = random_vgg(&device);
    let deep = DeepConfig {
        pre_sweeps: 3,
        ..DeepConfig::default()
    };
    let model = FeatureModel::Deep(deep_features(&vgg, a.clone(), b.clone(), deep).unwrap());
    let (p, q) = ([12.0, 10.0], [18.0, 17.0]);
    let landmarks = Landmarks::new(vec![p], vec![q], (32, 32)).unwrap();
    let shift = GlobalMap::similarity([0.0, 0.0], 0.0, 1.0, [6.0, 0.0]);
    #[derive(Default)]
    struct Start(Vec<Initialisation>, Events);
    impl Observer for Start {
        fn sweep(&mut self, e: &SweepEvent<'_>) {
            self.1.sweep(e);
        }
        fn initialised(&mut self, initialisation: &Initialisation) {
            self.0.push(initialisation.clone());
        }
    }
    let mut start = Start::default();
    let morph = Multilevel::new(config(2, 30))
        .unwrap()
        .with_landmarks(landmarks)
        .with_alignment(shift)
        .run_with(&device, a, b, &model, &mut start, &AtomicBool::new(false))
        .unwrap();
    assert_eq!(start.0.len(), 1);
    assert_eq!(start.0[0].halvings, vec![0; 3]);
    let phi = values(compose(&morph.grid, morph.state.deformations()));
    let met = LandmarkResiduals::of(&phi, (32, 32), &[(p, q)]).max;
    assert!(met < 1.0, "|Φ(p) − q| = {met} px");
}
