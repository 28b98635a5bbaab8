//! Wide-gamut colors (issue 16, item 5): a host working in ACEScg or
//! Rec.2020 converts to Linear Rec.709, where saturated colors have negative
//! components. They round-trip exactly through `bypass` and `strength` 0,
//! and the enhancement carries their out-of-gamut part through instead of
//! clipping it.

use std::sync::Arc;

use harmonizer_core::{Device, DeviceOptions, ParamValue, Session};

use crate::temporal::{sequence, Rendered};

/// ACEScg (AP1, D60) to Linear Rec.709 (D65), Bradford adapted.
#[allow(clippy::excessive_precision)]
const ACESCG_TO_709: [[f32; 3]; 3] = [
    [1.705_051, -0.621_792, -0.083_259],
    [-0.130_257, 1.140_805, -0.010_548],
    [-0.024_003, -0.128_969, 1.152_972],
];
/// Linear Rec.2020 to Linear Rec.709.
#[allow(clippy::excessive_precision)]
const REC2020_TO_709: [[f32; 3]; 3] = [
    [1.660_491, -0.587_641, -0.072_850],
    [-0.124_550, 1.132_900, -0.008_349],
    [-0.018_151, -0.100_579, 1.118_730],
];

/// The analytic scene's frames, their colors made saturated in the wide
/// space (one channel kept, one nearly removed, per region) and converted
/// to Linear Rec.709 with `m`.
fn wide(m: [[f32; 3]; 3]) -> Vec<Rendered> {
    let mut seq = sequence(0, 5, 96, 54);
    for r in &mut seq {
        for (i, px) in r.color.chunks_exact_mut(3).enumerate() {
            let l = (px[0] + px[1] + px[2]) / 3.0;
            let region = (i % r.w) * 3 / r.w;
            let mut c = [0.3 * l, 0.3 * l, 0.3 * l];
            c[region] = 1.6 * l;
            c[(region + 1) % 3] = 0.02 * l;
            for (o, row) in px.iter_mut().zip(m) {
                *o = row[0] * c[0] + row[1] * c[1] + row[2] * c[2];
            }
        }
    }
    seq
}

fn run(seq: &[Rendered], params: &[(&str, ParamValue)]) -> Vec<Vec<f32>> {
    let dev: Arc<Device> = Device::new(DeviceOptions {
        threads: 2,
        ..DeviceOptions::default()
    })
    .unwrap();
    let mut s = Session::new(dev, Default::default()).unwrap();
    for (k, v) in params {
        s.set(k, v.clone()).unwrap();
    }
    s.commit().unwrap();
    seq.iter()
        .enumerate()
        .map(|(t, r)| {
            let (out, report) = s
                .process(&r.input(true, true, true, t as i64), None)
                .unwrap();
            assert!(report.out_of_gamut > 0, "frame {t}: the report counts them");
            assert_eq!(report.sanitized, 0, "negative colors are not 'replaced'");
            let n = out.len();
            (0..n)
                .flat_map(|i| [out.data[i], out.data[n + i], out.data[2 * n + i]])
                .collect()
        })
        .collect()
}

fn negative_share(seq: &[Rendered]) -> f64 {
    let px = seq[0].color.chunks_exact(3);
    let n = px.len();
    px.filter(|p| p.iter().any(|&v| v < 0.0)).count() as f64 / n as f64
}

#[test]
fn out_of_gamut_colors_round_trip_through_bypass_and_strength_zero() {
    for (space, m) in [("ACEScg", ACESCG_TO_709), ("Rec.2020", REC2020_TO_709)] {
        let seq = wide(m);
        assert!(negative_share(&seq) > 0.3, "{space}: mostly out of gamut");
        for params in [
            vec![("backend", ParamValue::Str("bypass".into()))],
            vec![
                ("backend", ParamValue::Str("classical".into())),
                ("strength", ParamValue::Float(0.0)),
            ],
        ] {
            let outs = run(&seq, &params);
            for (t, (out, r)) in outs.iter().zip(&seq).enumerate() {
                let worst = out
                    .iter()
                    .zip(&r.color)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0f32, f32::max);
                assert!(
                    worst <= 1e-4,
                    "{space} {params:?} frame {t}: off by {worst}"
                );
            }
        }
    }
}

#[test]
fn the_enhancement_keeps_the_out_of_gamut_part() {
    for (space, m) in [("ACEScg", ACESCG_TO_709), ("Rec.2020", REC2020_TO_709)] {
        let seq = wide(m);
        let outs = run(&seq, &[("backend", ParamValue::Str("classical".into()))]);
        // On a clean render the enhancer changes little: the error on the
        // out-of-gamut pixels is far below what clipping them costs.
        let (mut err, mut clip, mut n) = (0.0f64, 0.0f64, 0usize);
        for (out, r) in outs.iter().zip(&seq) {
            for (o, i) in out.chunks_exact(3).zip(r.color.chunks_exact(3)) {
                if i.iter().any(|&v| v < 0.0) {
                    for c in 0..3 {
                        err += f64::from((o[c] - i[c]).abs());
                        clip += f64::from((i[c].max(0.0) - i[c]).abs());
                    }
                    n += 1;
                }
            }
        }
        let (err, clip) = (err / n as f64, clip / n as f64);
        eprintln!("{space}: {n} out-of-gamut pixels, mean error {err:.5}, clipped {clip:.5}");
        assert!(
            err < 0.25 * clip,
            "{space}: mean error {err:.5} on out-of-gamut pixels against {clip:.5} when clipped"
        );
        assert!(outs.iter().flatten().all(|v| v.is_finite()));
    }
}
