//! The prior of a model whose graph reads it (`prior.r|g|b` input channels,
//! manifest [`PriorSpec`]): the tile's encoded color with its holes filled,
//! first from the reprojected history frames (newest first, each under
//! what is still missing, gated where covered pixels are near), then by a
//! push-pull pyramid that fills from the background side of a depth edge.
//!
//! These are the operations of the trainer's `Enhancer.prior` with the
//! "chain" fill and `push_pull_depth` (`training/model.py`), in the same
//! order, on the same tile input the graph reads: a model trained with the
//! prior in its graph runs with it computed here (parity:
//! `training/tests/test_runtime_parity.py`). Computed in the graph, the
//! prior was dense full-resolution work (130 of ONNX Runtime's 460 ms at
//! 1920x1088 on 2 threads); here the full resolution is read twice (the
//! history chain, then the first halving) and the push writes only the
//! pixels not fully covered after the chain.
//!
//! The pull (the classical fill's halving, `crate::ops::inpaint::far::halve`)
//! halves each level to `ceil(size / 2)`, a missing row or
//! column counting as empty (the graph's zero padding); a pixel with data
//! of its own (the frame's coverage, not the history's) whose disparity
//! exceeds its 2x2 block's smallest by more than `depth_tol` (relative)
//! is left out of the block. The push completes each level from the
//! bilinear upsampling of the coarser one (half-pixel centres, edges
//! clamped), and the last step into the full resolution takes of each
//! pixel's four bilinear taps only those within `depth_tol` of the
//! farthest, renormalized.
//!
//! With the manifest's `edge_fill` (a runtime stage, not the trainer's):
//! the pixels the history left missing (weight under 0.95), and the
//! frame's own pixels within `NEAR_RADIUS` (4 px) of them that are nearer
//! than the farthest own pixel within that radius by `NEAR_TOL` (15 %; the near
//! side of a silhouette, which the fill would carry into the hole), are
//! also filled by the edge-continuing fill (`crate::ops::inpaint::edge`)
//! from the rest, and their missing part becomes that share of it and the
//! rest the push-pull's. Measured with model 1.12.0 (the quality
//! benchmark, 0.5 against none): warping error lower on all 36
//! reconstruction sequences, the holes 0.06 dB higher on average in
//! domain (+0.83 where a floor runs on past a reconstruction's border,
//! -0.30 at worst), +0.10 and +0.20 dB on two of the three out-of-domain
//! reconstructions (-0.01 on the third); about 6 ms at 1024x576 and 15 ms
//! at 1920x1080 on 2 threads (its cost follows the holes left, not the
//! frame). Its gradient unsigned, as OpenCV's (since 2026-11-29, model
//! 1.12.1, against the signed one): the holes +0.17 dB on held-out scene
//! 29, -0.02 to +0.07 on seven others, +0.00 to +0.02 out of domain; with
//! no history (a first frame, a cut) +0.48 and +0.20 dB on scenes 539 and
//! 29, -0.03 to +0.05 on the others.

use rayon::prelude::*;

use crate::model::{InputChannel, PriorSpec};
use crate::ops::inpaint::far::{halve, Level, Pixels, Px};

/// The classical backend's history gate (`crate::backend::classical`,
/// mirrored by the trainer's `GATE_RADIUS` and `history_weight`): the
/// share of covered pixels within this Chebyshev radius.
const GATE_RADIUS: usize = 3;

/// How much history a hole pixel takes from the share of covered pixels
/// around it: all up to 0.225, none from 0.3.
#[inline]
fn history_weight(share: f32) -> f32 {
    ((0.3 - share) / 0.075).clamp(0.0, 1.0)
}

/// The pyramid's levels, kept between frames (fresh memory costs a page
/// fault per 4 KiB on every frame).
#[derive(Default)]
struct Scratch {
    levels: Vec<Level>,
    filled: [Filled; 2],
    edge: EdgeScratch,
}

/// The edge-continuing fill's memory.
#[derive(Default)]
struct EdgeScratch {
    fill: crate::ops::inpaint::edge::EdgeFill,
    /// Full-frame planes holding, between fills, whatever the last wrote.
    planes: [Vec<f32>; 3],
    /// Per pixel: 0, or [`HOLE`] / [`SEEN`] while a fill runs.
    tag: Vec<u8>,
    holes: Vec<u32>,
    seen: Vec<u32>,
    /// Per hole: its prior with the edge fill.
    vals: Vec<[f32; 3]>,
}

const HOLE: u8 = 1;
const SEEN: u8 = 2;

/// Where the prior's inputs and outputs lie among a tile's input planes.
pub struct PriorChannels {
    spec: PriorSpec,
    color: [usize; 3],
    coverage: usize,
    /// Per history frame read: its color planes and its validity plane.
    history: Vec<([usize; 3], usize)>,
    disparity: Option<usize>,
    out: [usize; 3],
    scratch: std::sync::Mutex<Scratch>,
}

impl std::fmt::Debug for PriorChannels {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PriorChannels")
            .field("spec", &self.spec)
            .finish_non_exhaustive()
    }
}

impl PriorChannels {
    /// The planes of a validated manifest's channels; `None` for a model
    /// without prior channels.
    pub fn new(spec: Option<PriorSpec>, channels: &[InputChannel]) -> Option<PriorChannels> {
        let spec = spec?;
        let at = |want: InputChannel| {
            channels
                .iter()
                .position(|&c| c == want)
                .expect("validated manifest: the prior's channels are present")
        };
        Some(PriorChannels {
            spec,
            color: [0, 1, 2].map(|c| at(InputChannel::Color(c))),
            coverage: at(InputChannel::Coverage),
            history: (0..spec.frames)
                .map(|k| {
                    (
                        [0, 1, 2].map(|c| at(InputChannel::History(k, c))),
                        at(InputChannel::Valid(k)),
                    )
                })
                .collect(),
            disparity: (spec.depth_tol > 0.0).then(|| at(InputChannel::Disparity)),
            out: [0, 1, 2].map(|c| at(InputChannel::Prior(c))),
            scratch: Default::default(),
        })
    }

    /// Computes the prior into its planes of `tensor` (a tile's NCHW input,
    /// planes of `width` x `height`) from the others; `scratch` holds at
    /// least two planes.
    pub fn compute(
        &self,
        tensor: &mut [f32],
        (width, height): (usize, usize),
        scratch: &mut [f32],
        pool: &rayon::ThreadPool,
    ) {
        let np = width * height;
        assert!(tensor.len().is_multiple_of(np) && scratch.len() >= 2 * np);
        let mut outs: [Option<&mut [f32]>; 3] = [None, None, None];
        let mut ins: Vec<Option<&[f32]>> = Vec::new();
        for (i, plane) in tensor.chunks_exact_mut(np).enumerate() {
            match self.out.iter().position(|&o| o == i) {
                Some(c) => {
                    outs[c] = Some(plane);
                    ins.push(None);
                }
                None => {
                    let plane: &[f32] = plane;
                    ins.push(Some(plane));
                }
            }
        }
        let plane = |i: usize| ins[i].expect("an input plane, not the prior's");
        let [Some(r), Some(g), Some(b)] = outs else {
            unreachable!("three distinct prior planes")
        };
        let (weight, own) = scratch[..2 * np].split_at_mut(np);
        let src = Sources {
            color: self.color.map(plane),
            coverage: plane(self.coverage),
            history: self
                .history
                .iter()
                .map(|&(c, v)| (c.map(plane), plane(v)))
                .collect(),
            width,
            height,
        };
        let spec = self.spec;
        // Taken out of its lock, which no parallel work may hold (a worker
        // waiting in it could pick up another frame's prior and wait on
        // itself); a frame computed meanwhile starts from empty levels.
        let mut kept = std::mem::take(&mut *self.scratch.lock().unwrap_or_else(|p| p.into_inner()));
        pool.install(|| {
            chain(&src, &spec, [&mut *r, &mut *g, &mut *b], weight, own);
            let disp = self.disparity.map(plane);
            let edged = spec.edge_fill > 0.0
                && edge_prior(
                    &mut kept.edge,
                    [&*r, &*g, &*b],
                    weight,
                    own,
                    disp,
                    width,
                    height,
                );
            // Without a tolerance, a plain push-pull.
            let tol = (spec.depth_tol > 0.0).then_some(spec.depth_tol);
            let level0 = Fine {
                w: width,
                h: height,
                c: [&*r, &*g, &*b],
                wt: weight,
                own,
                disp,
            };
            let Scratch { levels, filled, .. } = &mut kept;
            // The pull: level 1 from the full resolution, then halvings.
            levels.resize_with(spec.levels, Level::default);
            halve(&level0, tol, &mut levels[0]);
            for l in 1..spec.levels {
                let (done, rest) = levels.split_at_mut(l);
                halve(&done[l - 1], tol, &mut rest[0]);
            }
            // The push, down to level 1: the filled color and disparity.
            let top = &levels[spec.levels - 1];
            let [mut f, mut next] = std::mem::take(filled);
            f.w = top.w;
            f.h = top.h;
            top.px
                .par_iter()
                .map(|p| {
                    let d = p[3].max(1e-4);
                    [
                        p[0] / d,
                        p[1] / d,
                        p[2] / d,
                        if p[4] > 0.0 { p[5] } else { 0.0 },
                    ]
                })
                .collect_into_vec(&mut f.px);
            for l in levels[..spec.levels - 1].iter().rev() {
                push(&f, l, &mut next);
                std::mem::swap(&mut f, &mut next);
            }
            finish(&f, [&mut *r, &mut *g, &mut *b], weight, width, tol);
            *filled = [f, next];
            if edged {
                // The push-pull's share of the missing part gives way to the
                // edge fill's: both priors hold the same known part.
                let share = spec.edge_fill;
                for (&i, v) in kept.edge.holes.iter().zip(&kept.edge.vals) {
                    let i = i as usize;
                    r[i] += share * (v[0] - r[i]);
                    g[i] += share * (v[1] - g[i]);
                    b[i] += share * (v[2] - b[i]);
                }
            }
        });
        *self.scratch.lock().unwrap_or_else(|p| p.into_inner()) = kept;
    }
}

/// The planes the history chain reads.
struct Sources<'a> {
    color: [&'a [f32]; 3],
    coverage: &'a [f32],
    history: Vec<([&'a [f32]; 3], &'a [f32])>,
    width: usize,
    height: usize,
}

/// The coverage a pixel keeps: clamped to 0..=1, 0 below the floor.
#[inline(always)]
fn kept(c: f32, floor: f32) -> f32 {
    let c = c.clamp(0.0, 1.0);
    if c < floor {
        0.0
    } else {
        c
    }
}

/// The known color (premultiplied by the weight) into `known`, the weight
/// into `weight`, the frame's own weight into `own`: the kept coverage,
/// then the history frames under what is missing.
fn chain(
    src: &Sources<'_>,
    spec: &PriorSpec,
    known: [&mut [f32]; 3],
    weight: &mut [f32],
    own: &mut [f32],
) {
    let w = src.width;
    let floor = spec.floor;
    let covered_at = floor.max(0.5);
    let [kr, kg, kb] = known;
    kr.par_chunks_mut(w)
        .zip(kg.par_chunks_mut(w))
        .zip(kb.par_chunks_mut(w))
        .zip(weight.par_chunks_mut(w))
        .zip(own.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, ((((kr, kg), kb), wt), ow))| {
            let row = y * w..(y + 1) * w;
            let cov = &src.coverage[row.clone()];
            let col: [&[f32]; 3] = src.color.map(|p| &p[row.clone()]);
            let mut partial = false;
            for x in 0..w {
                let c = kept(cov[x], floor);
                ow[x] = c;
                wt[x] = c;
                kr[x] = c * col[0][x];
                kg[x] = c * col[1][x];
                kb[x] = c * col[2][x];
                partial |= c != 1.0;
            }
            if !partial || src.history.is_empty() {
                return;
            }
            // The history under what is missing (where the weight is 1, it
            // adds exactly nothing).
            for x in 0..w {
                let mut wsum = wt[x];
                if wsum == 1.0 {
                    continue;
                }
                let gate = if spec.gate {
                    history_weight(share(src, y, x, floor, covered_at))
                } else {
                    1.0
                };
                let i = y * w + x;
                let mut k = [kr[x], kg[x], kb[x]];
                for (hc, hv) in &src.history {
                    let v = hv[i].clamp(0.0, 1.0) * gate;
                    let m = (1.0 - wsum) * v;
                    for (kc, p) in k.iter_mut().zip(hc) {
                        *kc += m * p[i];
                    }
                    wsum += m;
                }
                (kr[x], kg[x], kb[x]) = (k[0], k[1], k[2]);
                wt[x] = wsum;
            }
        });
}

/// The share of covered pixels (kept coverage at least `covered_at`) in
/// the square of [`GATE_RADIUS`] around (`x`, `y`), clipped at the edges:
/// the mean over its rows of each row's mean, as the graph's two average
/// pools compute it.
fn share(src: &Sources<'_>, y: usize, x: usize, floor: f32, covered_at: f32) -> f32 {
    let (w, h) = (src.width, src.height);
    let (x0, x1) = (x.saturating_sub(GATE_RADIUS), (x + GATE_RADIUS + 1).min(w));
    let (y0, y1) = (y.saturating_sub(GATE_RADIUS), (y + GATE_RADIUS + 1).min(h));
    let nx = (x1 - x0) as f32;
    let mut sum = 0.0f32;
    for yy in y0..y1 {
        let row = &src.coverage[yy * w + x0..yy * w + x1];
        let n = row
            .iter()
            .filter(|&&c| kept(c, floor) >= covered_at)
            .count();
        sum += n as f32 / nx;
    }
    sum / (y1 - y0) as f32
}

/// The full resolution as the pull reads it.
struct Fine<'a> {
    w: usize,
    h: usize,
    c: [&'a [f32]; 3],
    wt: &'a [f32],
    own: &'a [f32],
    disp: Option<&'a [f32]>,
}

impl Pixels for Fine<'_> {
    fn size(&self) -> (usize, usize) {
        (self.w, self.h)
    }

    #[inline]
    fn px(&self, i: usize) -> Px {
        [
            self.c[0][i],
            self.c[1][i],
            self.c[2][i],
            self.wt[i],
            self.own[i],
            self.disp.map_or(0.0, |d| d[i]),
        ]
    }
}

/// A level's complete color and disparity.
#[derive(Default)]
struct Filled {
    w: usize,
    h: usize,
    px: Vec<[f32; 4]>,
}

/// The taps of a bilinear resize along one axis from `from` to `to`
/// samples, as the graph's resize computes them (half-pixel centres, the
/// scale `to / from`, clamped at the edges: odd levels are not exactly
/// halved): per output sample, the two input samples and their weights.
fn resize_taps(from: usize, to: usize) -> Vec<(usize, usize, f32, f32)> {
    let scale = to as f32 / from as f32;
    (0..to)
        .map(|o| {
            let x = if to > 1 {
                ((o as f32 + 0.5) / scale - 0.5).clamp(0.0, (from - 1) as f32)
            } else {
                0.0
            };
            let i0 = (x as usize).min(from - 1);
            let i1 = (i0 + 1).min(from - 1);
            if i0 == i1 {
                (i0, i1, 0.5, 0.5)
            } else {
                let d = x - i0 as f32;
                (i0, i1, 1.0 - d, d)
            }
        })
        .collect()
}

/// One step of the push: `level`'s missing part (one minus its weight)
/// takes the bilinear upsampling of the coarser `f`; its disparity is its
/// own where it has data of its own, else the upsampled one.
fn push(f: &Filled, level: &Level, out: &mut Filled) {
    let (w, h) = (level.w, level.h);
    let tx = resize_taps(f.w, w);
    let ty = resize_taps(f.h, h);
    out.w = w;
    out.h = h;
    out.px.clear();
    out.px.resize(w * h, [0.0; 4]);
    out.px
        .par_chunks_mut(w)
        .with_min_len(4)
        .enumerate()
        .for_each(|(y, row)| {
            let (y0, y1, wy0, wy1) = ty[y];
            for (x, out) in row.iter_mut().enumerate() {
                let (x0, x1, wx0, wx1) = tx[x];
                let p = |yy: usize, xx: usize| f.px[yy * f.w + xx];
                let (a, b, c, d) = (p(y0, x0), p(y0, x1), p(y1, x0), p(y1, x1));
                let up: [f32; 4] = std::array::from_fn(|n| {
                    wy0 * (wx0 * a[n] + wx1 * b[n]) + wy1 * (wx0 * c[n] + wx1 * d[n])
                });
                let l = level.px[y * w + x];
                *out = [
                    l[0] + (1.0 - l[3]) * up[0],
                    l[1] + (1.0 - l[3]) * up[1],
                    l[2] + (1.0 - l[3]) * up[2],
                    if l[4] > 0.0 { l[5] } else { up[3] },
                ];
            }
        });
}

/// The bilinear weights of a 2x upsampling along one axis (pixel centres):
/// fine pixel `2i` takes coarse `i - 1` and `i` with 1/4 and 3/4, `2i + 1`
/// takes `i` and `i + 1` with 3/4 and 1/4, the edge's pixel standing for the
/// one past it (the graph's replicated padding: both taps are then that
/// pixel, so a tap beyond the edge never enters the farthest-tap limit, as
/// it would with `crate::ops::inpaint`'s clamped taps).
#[inline]
fn phase(fine: usize, coarse: usize) -> (usize, usize, f32, f32) {
    let i = fine / 2;
    if fine.is_multiple_of(2) {
        (i.saturating_sub(1), i.min(coarse - 1), 0.25, 0.75)
    } else {
        (i.min(coarse - 1), (i + 1).min(coarse - 1), 0.75, 0.25)
    }
}

/// The last step into the full resolution, at the pixels whose weight is
/// not 1 (the others keep their known color exactly): their missing part
/// takes the 2x upsampling of level 1, with a tolerance only its taps
/// within it of the farthest.
fn finish(f: &Filled, out: [&mut [f32]; 3], weight: &[f32], w: usize, tol: Option<f32>) {
    let [r, g, b] = out;
    assert!(
        w == 2 * f.w && weight.len() == w * 2 * f.h,
        "the full resolution is twice level 1 (tiles are multiples of the spatial multiple)"
    );
    r.par_chunks_mut(w)
        .zip(g.par_chunks_mut(w))
        .zip(b.par_chunks_mut(w))
        .zip(weight.par_chunks(w))
        .enumerate()
        .for_each(|(y, (((r, g), b), wt))| {
            let (y0, y1, wy0, wy1) = phase(y, f.h);
            for x in 0..w {
                let a = wt[x];
                if a == 1.0 {
                    continue;
                }
                let (x0, x1, wx0, wx1) = phase(x, f.w);
                let t = [
                    f.px[y0 * f.w + x0],
                    f.px[y0 * f.w + x1],
                    f.px[y1 * f.w + x0],
                    f.px[y1 * f.w + x1],
                ];
                let keep: [f32; 4] = match tol {
                    Some(tol) => {
                        let far = t.iter().map(|p| p[3]).fold(f32::INFINITY, f32::min);
                        let limit = far * (1.0 + tol);
                        t.map(|p| if p[3] <= limit { 1.0 } else { 0.0 })
                    }
                    None => [1.0; 4],
                };
                // As the graph sums: across each tap row, then the rows.
                let col = |n: usize| -> f32 {
                    let top = keep[0] * t[0][n] * wx0 + keep[1] * t[1][n] * wx1;
                    let bottom = keep[2] * t[2][n] * wx0 + keep[3] * t[3][n] * wx1;
                    top * wy0 + bottom * wy1
                };
                let den = {
                    let top = keep[0] * wx0 + keep[1] * wx1;
                    let bottom = keep[2] * wx0 + keep[3] * wx1;
                    top * wy0 + bottom * wy1
                };
                let miss = 1.0 - a;
                r[x] += miss * (col(0) / den);
                g[x] += miss * (col(1) / den);
                b[x] += miss * (col(2) / den);
            }
        });
}

/// Near-side test: radius (pixels) and relative disparity.
const NEAR_RADIUS: usize = 4;
const NEAR_TOL: f32 = 0.15;

/// The edge-continuing fill of the chain's result (`known` premultiplied
/// by `weight`): the holes (weight under 0.95, and the frame's own pixels
/// within [`NEAR_RADIUS`] of one that are nearer than the farthest own
/// pixel within it by [`NEAR_TOL`]) in `edge.holes`, in pixel order, with
/// their prior (the known part plus the missing part filled) in
/// `edge.vals`; false (nothing found) where every pixel is known.
fn edge_prior(
    edge: &mut EdgeScratch,
    known: [&[f32]; 3],
    weight: &[f32],
    own: &[f32],
    disp: Option<&[f32]>,
    w: usize,
    h: usize,
) -> bool {
    let np = w * h;
    // The fill ranks pixels in 32 bits (a tile is far smaller: at most the
    // manifest's tile size squared).
    if np >= u32::MAX as usize {
        return false;
    }
    edge.holes.clear();
    edge.holes.par_extend(
        weight
            .par_iter()
            .enumerate()
            .filter(|&(_, &x)| x < 0.95)
            .map(|(i, _)| i as u32),
    );
    if edge.holes.is_empty() {
        return false;
    }
    if edge.tag.len() != np {
        edge.tag = vec![0; np];
        for p in &mut edge.planes {
            *p = vec![0.0; np];
        }
    }
    for &i in &edge.holes {
        edge.tag[i as usize] = HOLE;
    }
    // The pixels within `r` (Chebyshev) of a hole that are not holes, each
    // once, tagged SEEN.
    let around = |tag: &mut [u8], seen: &mut Vec<u32>, holes: &[u32], r: usize| {
        for &i in holes {
            let (x, y) = (i as usize % w, i as usize / w);
            for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                    let j = yy * w + xx;
                    if tag[j] == 0 {
                        tag[j] = SEEN;
                        seen.push(j as u32);
                    }
                }
            }
        }
    };
    edge.seen.clear();
    if let Some(disp) = disp {
        let r = NEAR_RADIUS;
        around(&mut edge.tag, &mut edge.seen, &edge.holes, r);
        let near: Vec<u32> = edge
            .seen
            .par_iter()
            .copied()
            .filter(|&i| {
                let i = i as usize;
                if own[i] < 0.5 {
                    return false;
                }
                let (x, y) = (i % w, i / w);
                let mut far = f32::INFINITY;
                for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                    for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                        let j = yy * w + xx;
                        if own[j] >= 0.5 {
                            far = far.min(disp[j]);
                        }
                    }
                }
                disp[i] > far * (1.0 + NEAR_TOL)
            })
            .collect();
        for &i in &near {
            edge.tag[i as usize] = HOLE;
        }
        edge.holes.extend(near);
        edge.holes.par_sort_unstable();
    }
    // The known values the fill reads.
    let reach = crate::ops::inpaint::edge::EDGE_RADIUS as usize + 1;
    around(&mut edge.tag, &mut edge.seen, &edge.holes, reach);
    for &i in &edge.seen {
        let i = i as usize;
        if edge.tag[i] == SEEN {
            for (plane, k) in edge.planes.iter_mut().zip(known) {
                plane[i] = k[i] / weight[i];
            }
        }
    }
    let [p0, p1, p2] = &mut edge.planes;
    edge.fill.fill([p0, p1, p2], &edge.holes, w, h);
    for &i in edge.holes.iter().chain(&edge.seen) {
        edge.tag[i as usize] = 0;
    }
    let planes = &edge.planes;
    edge.vals.clear();
    edge.vals.par_extend(edge.holes.par_iter().map(|&i| {
        let i = i as usize;
        let miss = 1.0 - weight[i];
        std::array::from_fn(|c| known[c][i] + miss * planes[c][i])
    }));
    true
}
