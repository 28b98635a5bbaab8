//! The session: reset equals cold start, determinism (twice, 1 vs 2 threads),
//! a cancelled or failed frame leaves the state unchanged, gap policy, size
//! change, scene cuts, warnings. Runs the classical backend (it uses the
//! reprojected history) on the analytic scene of `temporal.rs`.

use std::sync::Arc;

use harmonizer_core::frame::{FrameInput, ImageView};
use harmonizer_core::session::ResetReason;
use harmonizer_core::{Device, DeviceOptions, Error, Image, ParamValue, Session};

use crate::temporal::{camera_at, render, sequence, Look, Rendered};

const W: usize = 192;
const H: usize = 108;

fn device(threads: usize) -> Arc<Device> {
    Device::new(DeviceOptions {
        threads,
        ..DeviceOptions::default()
    })
    .unwrap()
}

fn session(dev: &Arc<Device>, extra: &[(&str, ParamValue)]) -> Session {
    let mut s = Session::new(dev.clone(), Default::default()).unwrap();
    s.set("backend", ParamValue::Str("classical".into()))
        .unwrap();
    // The history must change every frame's output for these tests to be
    // able to fail: the whole frame is stabilized even without holes.
    s.set("stabilize_all", ParamValue::Bool(true)).unwrap();
    for (k, v) in extra {
        s.set(k, v.clone()).unwrap();
    }
    s.commit().unwrap();
    s
}

fn input(r: &Rendered, index: i64) -> FrameInput<'_> {
    r.input(true, true, true, index)
}

fn same(a: &Image, b: &Image) -> bool {
    a.width == b.width
        && a.height == b.height
        && a.data.len() == b.data.len()
        && a.data
            .iter()
            .zip(&b.data)
            .all(|(x, y)| x.to_bits() == y.to_bits())
}

/// Runs frames `t0..=t1` of `seq` (whose first frame is number `first`).
fn run(s: &mut Session, seq: &[Rendered], first: i64, t0: i64, t1: i64) -> Vec<Image> {
    (t0..=t1)
        .map(|t| {
            s.process(&input(&seq[(t - first) as usize], t), None)
                .unwrap()
                .0
        })
        .collect()
}

#[test]
fn reset_equals_cold_start_bit_for_bit() {
    let seq = sequence(0, 6, W, H);
    let dev = device(2);
    let mut warm = session(&dev, &[]);
    run(&mut warm, &seq, 0, 0, 3);
    let mut kept = warm_clone(&dev, &seq);
    warm.reset();
    let after_reset = run(&mut warm, &seq, 0, 4, 6);
    let mut cold = session(&dev, &[]);
    let cold_out = run(&mut cold, &seq, 0, 4, 6);
    for (a, b) in after_reset.iter().zip(&cold_out) {
        assert!(same(a, b), "output after reset differs from a cold start");
    }
    // The history matters, so the comparison above can fail.
    let with_history = run(&mut kept, &seq, 0, 4, 4);
    assert!(
        !same(&with_history[0], &cold_out[0]),
        "the history changes the output"
    );

    // The per-frame reset flag does the same.
    let mut flagged = session(&dev, &[]);
    run(&mut flagged, &seq, 0, 0, 3);
    let mut f = input(&seq[4], 4);
    f.reset = true;
    let (out, report) = flagged.process(&f, None).unwrap();
    assert_eq!(report.reset, Some(ResetReason::Requested));
    assert!(same(&out, &cold_out[0]));
}

/// A session that has seen frames 0..=3.
fn warm_clone(dev: &Arc<Device>, seq: &[Rendered]) -> Session {
    let mut s = session(dev, &[]);
    run(&mut s, seq, 0, 0, 3);
    s
}

#[test]
fn same_inputs_give_bit_identical_outputs_with_1_and_2_threads() {
    let seq = sequence(0, 5, W, H);
    let outs: Vec<Vec<Image>> = [1, 2, 2]
        .iter()
        .map(|&threads| {
            let dev = device(threads);
            let mut s = session(&dev, &[]);
            run(&mut s, &seq, 0, 0, 5)
        })
        .collect();
    for other in &outs[1..] {
        for (t, (a, b)) in outs[0].iter().zip(other).enumerate() {
            assert!(same(a, b), "frame {t} differs between runs / thread counts");
        }
    }
}

#[test]
fn cancelled_or_failed_frame_leaves_state_unchanged() {
    let seq = sequence(0, 4, W, H);
    let dev = device(2);
    let mut reference = session(&dev, &[]);
    let expected = run(&mut reference, &seq, 0, 0, 4);

    // How many progress calls one frame makes.
    let mut calls = 0;
    let mut probe = session(&dev, &[]);
    probe
        .process(
            &input(&seq[0], 0),
            Some(&mut |_| {
                calls += 1;
                true
            }),
        )
        .unwrap();
    assert!(calls >= 2, "progress is reported ({calls} calls)");

    for cancel_at in 1..=calls {
        let mut s = session(&dev, &[]);
        run(&mut s, &seq, 0, 0, 1);
        let mut n = 0;
        let err = s
            .process(
                &input(&seq[2], 2),
                Some(&mut |_| {
                    n += 1;
                    n < cancel_at
                }),
            )
            .unwrap_err();
        assert!(matches!(err, Error::Cancelled(_)), "{err}");
        assert_eq!(s.history_len(), 2);
        let rest = run(&mut s, &seq, 0, 2, 4);
        for (t, (a, b)) in rest.iter().zip(&expected[2..]).enumerate() {
            assert!(
                same(a, b),
                "cancel at call {cancel_at}: frame {} differs",
                t + 2
            );
        }
    }

    // A frame with a bad AOV fails and changes nothing.
    let mut s = session(&dev, &[]);
    run(&mut s, &seq, 0, 0, 1);
    let small = vec![1.0f32; 10 * 10];
    let mut bad = input(&seq[2], 2);
    bad.depth = Some(ImageView::from_f32("depth", &small, 10, 10, 1).unwrap());
    let err = s.process(&bad, None).unwrap_err().to_string();
    assert!(err.contains("depth") && err.contains("10x10"), "{err}");
    let rest = run(&mut s, &seq, 0, 2, 4);
    for (a, b) in rest.iter().zip(&expected[2..]) {
        assert!(same(a, b), "a failed frame changed the state");
    }
}

#[test]
fn frame_gap_resets_or_keeps_by_policy() {
    let seq = sequence(0, 5, W, H);
    let dev = device(2);
    let mut cold = session(&dev, &[]);
    let cold5 = cold.process(&input(&seq[5], 5), None).unwrap().0;

    let mut s = session(&dev, &[]);
    run(&mut s, &seq, 0, 0, 2);
    let (out, report) = s.process(&input(&seq[5], 5), None).unwrap();
    assert_eq!(report.reset, Some(ResetReason::FrameGap));
    assert_eq!(report.history_used, 0);
    assert!(
        report
            .warnings
            .iter()
            .any(|w| w.contains("frame 5") && w.contains("frame 2")),
        "{:?}",
        report.warnings
    );
    assert!(same(&out, &cold5), "a gap reset is a cold start");

    let mut s = session(&dev, &[("gap_policy", ParamValue::Str("keep".into()))]);
    run(&mut s, &seq, 0, 0, 2);
    let (out, report) = s.process(&input(&seq[5], 5), None).unwrap();
    assert_eq!(report.reset, None);
    assert_eq!(report.history_used, 3);
    assert!(
        report
            .warnings
            .iter()
            .any(|w| w.contains("not consecutive") && w.contains("kept")),
        "{:?}",
        report.warnings
    );
    assert!(!same(&out, &cold5));
}

#[test]
fn size_and_layout_changes_reset() {
    let dev = device(2);
    let seq = sequence(0, 1, W, H);
    let small = sequence(2, 2, W / 2, H / 2);
    let mut s = session(&dev, &[]);
    let (_, r) = s.process(&input(&seq[0], 0), None).unwrap();
    assert_eq!(r.reset, Some(ResetReason::FirstFrame));
    let (_, r) = s.process(&input(&seq[1], 1), None).unwrap();
    assert_eq!(r.reset, None);
    assert_eq!(r.history_used, 1);
    let (out, r) = s.process(&input(&small[0], 2), None).unwrap();
    assert_eq!(r.reset, Some(ResetReason::SizeChanged));
    assert_eq!((out.width, out.height), (W / 2, H / 2));
    let (_, r) = s
        .process(&small[0].input(false, true, true, 3), None)
        .unwrap();
    assert_eq!(r.reset, Some(ResetReason::LayoutChanged));
}

#[test]
fn scene_cut_resets_but_exposure_flicker_does_not() {
    let dev = device(2);
    let seq = sequence(0, 3, W, H);
    let mut s = session(&dev, &[]);
    run(&mut s, &seq, 0, 0, 1);
    let flicker =
        render(Look::Main, camera_at(2.0, W, H), camera_at(1.0, W, H), W, H).exposed(1.25);
    let (_, r) = s.process(&input(&flicker, 2), None).unwrap();
    assert_eq!(r.reset, None, "+25 % exposure is not a cut");
    let flicker =
        render(Look::Main, camera_at(3.0, W, H), camera_at(2.0, W, H), W, H).exposed(0.75);
    let (_, r) = s.process(&input(&flicker, 3), None).unwrap();
    assert_eq!(r.reset, None, "-25 % exposure is not a cut");
    let cam = camera_at(4.0, W, H);
    let cut = render(Look::Other, cam, cam, W, H);
    let f = input(&cut, 4);
    let (out, r) = s.process(&f, None).unwrap();
    assert_eq!(r.reset, Some(ResetReason::SceneCut));
    assert_eq!(r.history_used, 0);
    let mut cold = session(&dev, &[]);
    assert!(
        same(&out, &cold.process(&f, None).unwrap().0),
        "a cut is a cold start"
    );

    // Disabled: no reset.
    let mut s = session(&dev, &[("scene_cut_detection", ParamValue::Bool(false))]);
    run(&mut s, &seq, 0, 0, 1);
    let f = input(&cut, 2);
    assert_eq!(s.process(&f, None).unwrap().1.reset, None);
}

/// A cut found after the classical backend ran with the history (scored
/// from what its stabilization pass recorded) leaves the session as a
/// reset at that frame would: the cut frame is a cold start, and the frames
/// after it continue from it bit for bit (issue 2).
#[test]
fn a_cut_found_after_the_backend_continues_as_a_reset_would() {
    let dev = device(2);
    let seq = sequence(0, 2, W, H);
    let cam = |t: i64| camera_at(t as f32, W, H);
    let other: Vec<Rendered> = (3..=5)
        .map(|t| render(Look::Other, cam(t), cam(t - 1), W, H))
        .collect();
    let mut s = session(&dev, &[]);
    let mut reset = session(&dev, &[]);
    run(&mut s, &seq, 0, 0, 2);
    run(&mut reset, &seq, 0, 0, 2);
    for (k, r) in other.iter().enumerate() {
        let t = 3 + k as i64;
        let (out, rep) = s.process(&input(r, t), None).unwrap();
        let mut f = input(r, t);
        f.reset = k == 0;
        let (want, wrep) = reset.process(&f, None).unwrap();
        assert_eq!(
            rep.reset,
            (k == 0).then_some(ResetReason::SceneCut),
            "frame {t}"
        );
        assert_eq!(
            wrep.reset,
            (k == 0).then_some(ResetReason::Requested),
            "frame {t}"
        );
        assert_eq!(rep.history_used, k, "frame {t}");
        assert!(same(&out, &want), "frame {t}: not what a reset gives");
        // The detector ran on every frame with history.
        assert!(
            rep.stages.0.iter().any(|(n, _)| n == "scene_cut"),
            "frame {t}: {:?}",
            rep.stages
        );
    }
}

#[test]
fn warnings_for_nan_inputs_and_huge_motion_vectors() {
    let dev = device(2);
    let mut seq = sequence(0, 1, W, H);
    seq[1].color[7] = f32::NAN;
    seq[1].color[8] = -1.0;
    seq[1].depth[5] = f32::NAN;
    seq[1].motion[0] = 1e6;
    let mut s = session(&dev, &[]);
    s.process(&input(&seq[0], 10), None).unwrap();
    let (out, r) = s.process(&input(&seq[1], 11), None).unwrap();
    // The NaN is replaced; the finite negative sample is an out-of-gamut
    // color and passes through (no warning).
    assert_eq!(r.sanitized, 1);
    assert_eq!(r.out_of_gamut, 1);
    let all = r.warnings.join("\n");
    assert!(
        all.contains("frame 11: 1 color samples were NaN or infinite"),
        "{all}"
    );
    assert!(all.contains("frame 11: 1 AOV samples were NaN"), "{all}");
    assert!(
        all.contains("frame 11: 1 motion vectors are longer than the image (192x108)"),
        "{all}"
    );
    assert!(out.data.iter().all(|v| v.is_finite()));
}

/// Regression (issue 2): a frame too large to allocate aborted the process
/// in the recycler's allocation. It is refused before anything is
/// allocated or read, naming the size and the limit, and the session goes
/// on as if the call never happened.
#[test]
fn a_frame_too_large_for_memory_is_refused_and_changes_nothing() {
    use harmonizer_core::frame::{try_zeros, Recycler};
    use harmonizer_core::FrameShape;
    let seq = sequence(0, 3, W, H);
    let dev = device(2);
    // Without a limit: the machine's memory (frames of 2^20 x 2^20 and
    // 60000 x 60000 need terabytes).
    let s = session(&dev, &[]);
    assert_eq!(dev.memory_budget().1, "memory of this machine");
    for side in [1usize << 20, 60000] {
        let e = s.check_memory(&FrameShape::new(side, side)).unwrap_err();
        let msg = e.to_string();
        assert!(matches!(e, Error::OutOfMemory(_)), "{msg}");
        assert!(
            msg.contains(&format!("{side}x{side}")) && msg.contains("memory of this machine"),
            "{msg}"
        );
    }
    // Sizes whose arithmetic overflows.
    let e = s
        .check_memory(&FrameShape::new(usize::MAX / 2, 3))
        .unwrap_err();
    assert!(matches!(e, Error::OutOfMemory(_)), "{e}");
    // An allocation the allocator refuses is an error, not an abort. The
    // results are kept (`black_box`): an optimizer may take an allocation
    // nothing reads for granted and never ask the allocator.
    use std::hint::black_box;
    assert!(matches!(
        black_box(try_zeros(1 << 60)),
        Err(Error::OutOfMemory(_))
    ));
    let r = Recycler::new();
    assert!(matches!(
        black_box(r.try_take(1 << 44)),
        Err(Error::OutOfMemory(_))
    ));
    assert!(matches!(
        black_box(r.try_image(1 << 30, 1 << 30, 4)),
        Err(Error::OutOfMemory(_))
    ));
    assert!(matches!(
        black_box(r.take_zeroed(1 << 40, 1 << 30)),
        Err(Error::OutOfMemory(_))
    ));

    // With memory_limit 64 MiB: 20000 x 20000 is refused, and so is a frame
    // the session holds (a 2048 x 2048 color buffer, zeros never read: the
    // refusal comes first), through `process`.
    let limit = 64 << 20;
    let small = Device::new(DeviceOptions {
        threads: 2,
        memory_limit: limit,
        ..DeviceOptions::default()
    })
    .unwrap();
    assert_eq!(small.memory_budget(), (limit, "device memory_limit"));
    let mut reference = session(&small, &[]);
    let expected = run(&mut reference, &seq, 0, 0, 3);
    let mut s = session(&small, &[]);
    run(&mut s, &seq, 0, 0, 1);
    let e = s.check_memory(&FrameShape::new(20000, 20000)).unwrap_err();
    assert!(
        e.to_string().contains("20000x20000") && e.to_string().contains("67108864"),
        "{e}"
    );
    let big = vec![0.0f32; 2048 * 2048 * 3];
    let mut huge = FrameInput::new(ImageView::from_f32("color", &big, 2048, 2048, 3).unwrap());
    huge.frame_index = Some(2);
    let e = s.process(&huge, None).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, Error::OutOfMemory(_)), "{msg}");
    assert!(
        msg.contains("2048x2048") && msg.contains("device memory_limit of 67108864 bytes"),
        "{msg}"
    );
    assert_eq!(s.history_len(), 2);
    // The same frame number again: nothing of the failed call was kept.
    let rest = run(&mut s, &seq, 0, 2, 3);
    for (t, (a, b)) in rest.iter().zip(&expected[2..]).enumerate() {
        assert!(
            same(a, b),
            "frame {} after the refused frame differs",
            t + 2
        );
    }
}

/// Regression (issue 11): frame numbers i64::MAX then i64::MIN counted as
/// consecutive (wrapping arithmetic); they are a gap.
#[test]
fn frame_numbers_do_not_wrap_around() {
    let seq = sequence(0, 2, W, H);
    let dev = device(2);
    let mut s = session(&dev, &[]);
    s.process(&input(&seq[0], i64::MAX), None).unwrap();
    let (_, r) = s.process(&input(&seq[1], i64::MIN), None).unwrap();
    assert_eq!(r.reset, Some(ResetReason::FrameGap));
    assert_eq!(r.history_used, 0);
    // With gap_policy keep, a kept gap warns.
    let mut keep = session(&dev, &[("gap_policy", ParamValue::Str("keep".into()))]);
    keep.process(&input(&seq[0], i64::MAX), None).unwrap();
    let (_, r) = keep.process(&input(&seq[1], i64::MIN), None).unwrap();
    assert_eq!(r.reset, None);
    assert!(
        r.warnings.iter().any(|w| w.contains("not consecutive")),
        "{:?}",
        r.warnings
    );
    let (_, r) = s.process(&input(&seq[2], i64::MIN + 1), None).unwrap();
    assert_eq!(r.reset, None, "i64::MIN + 1 follows i64::MIN");
}

/// Regression (issue 13): normals were accepted and ignored, NaN in them
/// unreported. They are validated like the other AOVs: size and channels
/// checked, NaN and infinite samples counted and warned; the classical
/// backend does not read them, so its output is the same with or without.
#[test]
fn normals_are_validated_and_their_bad_samples_warned() {
    let seq = sequence(0, 1, W, H);
    let dev = device(2);
    let mut normal: Vec<f32> = (0..W * H).flat_map(|_| [0.0f32, 0.0, -1.0]).collect();
    normal[4] = f32::NAN;
    normal[9] = f32::INFINITY;
    normal[10] = f32::NEG_INFINITY;
    for backend in ["classical", "bypass"] {
        let set = [("backend", ParamValue::Str(backend.into()))];
        let mut with = session(&dev, &set);
        let mut without = session(&dev, &set);
        for t in 0..2 {
            let mut f = input(&seq[t as usize], 7 + t);
            let (b, rb) = without.process(&f, None).unwrap();
            f.normal = Some(ImageView::from_f32("normal", &normal, W, H, 3).unwrap());
            let (a, ra) = with.process(&f, None).unwrap();
            assert!(same(&a, &b), "{backend}: normals change the output");
            let all = ra.warnings.join("\n");
            assert!(
                all.contains(&format!(
                    "frame {}: 3 normal samples were NaN or infinite",
                    7 + t
                )),
                "{backend}: {all}"
            );
            assert!(!rb.warnings.join("\n").contains("normal"));
        }
        // Wrong size and channel count are refused, naming the AOV.
        let two = vec![0.0f32; W * H * 2];
        let mut f = input(&seq[0], 100);
        f.normal = Some(ImageView::from_f32("normal", &two, W, H, 2).unwrap());
        let e = with.process(&f, None).unwrap_err().to_string();
        assert!(e.contains("normal") && e.contains("3 channel"), "{e}");
        f.normal = Some(ImageView::from_f32("normal", &two, W / 2, H, 3).unwrap());
        let e = with.process(&f, None).unwrap_err().to_string();
        assert!(e.contains("normal") && e.contains("differs"), "{e}");
    }
}
