//! Scene-cut detection: does the current frame continue the history?
//!
//! The current frame is compared with history frame 0 reprojected into its
//! view, on a grid of cells (about 64 across) where the reprojection is valid:
//! cell means of log-luminance and of chromaticity, from a sparse lattice of
//! about 4 x 4 pixels per cell (only those pixels are reprojected, so the
//! detector costs well under a millisecond at 1920x1080). A global exposure change
//! (flicker) is one offset of log-luminance shared by all cells, so the median
//! offset is removed first; a cell mismatches when what is left is larger than
//! [`LOG_TOLERANCE`] or its chromaticity moved more than [`CHROMA_TOLERANCE`].
//! A cut is: more than `threshold` of the compared cells mismatch, or the
//! exposure jumped by more than [`MAX_EXPOSURE_JUMP`] (natural log), or the
//! depth/motion reprojection found almost nothing valid
//! (fewer than [`MIN_VALID_CELLS`] of the cells).

use std::borrow::Cow;
use std::sync::OnceLock;

use rayon::prelude::*;

use super::{HistoryView, ReprojectionMode};
use crate::frame::PreparedFrame;

/// Residual log-luminance difference (natural log) above which a cell mismatches.
pub const LOG_TOLERANCE: f32 = 0.3;
/// Chromaticity distance (L1 of r/(r+g+b), g/(r+g+b)) above which a cell mismatches.
pub const CHROMA_TOLERANCE: f32 = 0.08;
/// A global exposure change beyond this (natural log, about 2 stops) is a cut.
pub const MAX_EXPOSURE_JUMP: f32 = 1.4;
/// With depth or motion reprojection, fewer valid cells than this fraction is a cut.
pub const MIN_VALID_CELLS: f32 = 0.05;

/// What the detector measured for one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneCutScore {
    /// Cells in the grid.
    pub cells: usize,
    /// Cells where the reprojected history was valid enough to compare.
    pub compared: usize,
    /// Fraction of the compared cells that mismatch (0 when none compared).
    pub mismatch: f32,
    /// Median log-luminance offset, current minus history (exposure change).
    pub exposure_offset: f32,
    /// True when validity comes from depth or motion vectors (not assumed).
    pub geometric: bool,
}

impl SceneCutScore {
    /// True when this score means a cut for `threshold` (fraction of mismatching cells).
    pub fn is_cut(&self, threshold: f32) -> bool {
        if self.cells == 0 {
            return false;
        }
        if (self.compared as f32) < MIN_VALID_CELLS * self.cells as f32 {
            // Nothing of the history is visible: a cut if depth or motion say so.
            return self.geometric;
        }
        self.mismatch > threshold || self.exposure_offset.abs() > MAX_EXPOSURE_JUMP
    }
}

#[derive(Clone, Copy, Default)]
struct Cell {
    weight: f32,
    area: f32,
    cur: [f32; 3],
    hist: [f32; 3],
}

/// The sparse lattice of pixels the detector compares: a grid of square
/// cells of `cell` pixels (about 64 across the longer side, at least 8
/// pixels), each sampled every `step` pixels (about 4 x 4 per cell) from
/// `step / 2` into the cell. Samples are kept row-major: lattice row `r`
/// (image row [`Lattice::rows`]`[r]`), column `c` (image column
/// [`Lattice::columns`]`[c]`) at `r * columns.len() + c`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Lattice {
    width: usize,
    height: usize,
    cell: usize,
    /// Image rows of the lattice, ascending.
    rows: Vec<usize>,
    /// Image columns of the lattice, ascending.
    columns: Vec<usize>,
    /// For each image row, its lattice row (`u32::MAX`: none).
    row_of: Vec<u32>,
}

impl Lattice {
    /// The lattice of a `width` x `height` frame.
    pub fn new(width: usize, height: usize) -> Lattice {
        let cell = (width.max(height).div_ceil(64)).max(8);
        let step = (cell / 4).max(1);
        let along = |n: usize| -> Vec<usize> {
            (0..n.div_ceil(cell))
                .flat_map(|g| (g * cell + step / 2..((g + 1) * cell).min(n)).step_by(step))
                .collect()
        };
        let (rows, columns) = (along(height), along(width));
        let mut row_of = vec![u32::MAX; height];
        for (r, &y) in rows.iter().enumerate() {
            row_of[y] = r as u32;
        }
        Lattice {
            width,
            height,
            cell,
            rows,
            columns,
            row_of,
        }
    }

    /// Image rows of the lattice, ascending.
    pub fn rows(&self) -> &[usize] {
        &self.rows
    }

    /// Image columns of the lattice, ascending.
    pub fn columns(&self) -> &[usize] {
        &self.columns
    }

    /// The lattice row at image row `y`, if it is one.
    #[inline]
    pub fn row_of(&self, y: usize) -> Option<usize> {
        self.row_of
            .get(y)
            .filter(|&&r| r != u32::MAX)
            .map(|&r| r as usize)
    }

    /// Samples in the lattice.
    pub fn len(&self) -> usize {
        self.rows.len() * self.columns.len()
    }

    /// True for a frame without pixels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Four values of row `y` at the lattice's columns: `f(x)` for each
    /// column `x`.
    pub fn take_row(&self, f: impl Fn(usize) -> [f32; 4]) -> Vec<[f32; 4]> {
        self.columns.iter().map(|&x| f(x)).collect()
    }
}

/// Lattice samples filled row by row from parallel passes: each lattice
/// row is set once ([`LatticeRows::set`]) by the pass that has that image
/// row in cache.
#[derive(Debug)]
pub struct LatticeRows<'l> {
    lattice: &'l Lattice,
    rows: Vec<OnceLock<Vec<[f32; 4]>>>,
}

impl<'l> LatticeRows<'l> {
    /// Empty rows of `lattice`.
    pub fn new(lattice: &'l Lattice) -> LatticeRows<'l> {
        let rows = (0..lattice.rows.len()).map(|_| OnceLock::new()).collect();
        LatticeRows { lattice, rows }
    }

    /// The lattice.
    pub fn lattice(&self) -> &'l Lattice {
        self.lattice
    }

    /// Records image row `y` when it is a lattice row (`f(x)` at each of
    /// the lattice's columns, see [`Lattice::take_row`]); a row already
    /// recorded keeps its first values.
    #[inline]
    pub fn set(&self, y: usize, f: impl Fn(usize) -> [f32; 4]) {
        if let Some(r) = self.lattice.row_of(y) {
            if self.rows[r].get().is_none() {
                let _ = self.rows[r].set(self.lattice.take_row(f));
            }
        }
    }

    /// Every sample, row-major, once every lattice row is recorded.
    pub fn finish(self) -> Option<Vec<[f32; 4]>> {
        let mut out = Vec::with_capacity(self.lattice.len());
        for r in self.rows {
            out.extend(r.into_inner()?);
        }
        Some(out)
    }
}

/// The current frame at `lattice`: premultiplied RGB and the coverage (1
/// when absent), the samples kept while the frame was prepared when there
/// are any ([`PreparedFrame::scene_samples`]), else read from its planes
/// (which must be there).
pub fn current_samples<'f>(lattice: &Lattice, current: &'f PreparedFrame) -> Cow<'f, [[f32; 4]]> {
    if let Some(s) = current
        .scene_samples
        .as_deref()
        .filter(|s| s.len() == lattice.len())
    {
        return Cow::Borrowed(s);
    }
    let (w, n) = (current.width(), current.width() * current.height());
    let (cur, cov) = (&current.color.data, current.coverage.as_deref());
    let mut out = Vec::with_capacity(lattice.len());
    for &y in lattice.rows() {
        out.extend(lattice.take_row(|x| {
            let p = y * w + x;
            [
                cur[p],
                cur[n + p],
                cur[2 * n + p],
                cov.map_or(1.0, |c| c[p]),
            ]
        }));
    }
    Cow::Owned(out)
}

/// History frame 0 of `view` reprojected at `lattice`: RGB and validity,
/// pixel by pixel ([`HistoryView::sampler`]), in parallel on the view's pool.
pub fn history_samples(lattice: &Lattice, view: &HistoryView<'_>) -> Vec<[f32; 4]> {
    let at = view.sampler(0);
    let row = |&y: &usize| -> Vec<[f32; 4]> {
        lattice.take_row(|x| {
            let (c, v) = at.at(y, x);
            [c[0], c[1], c[2], v]
        })
    };
    let rows: Vec<Vec<[f32; 4]>> = match view.pool() {
        Some(pool) => pool.install(|| lattice.rows().par_iter().map(row).collect()),
        None => lattice.rows().iter().map(row).collect(),
    };
    rows.concat()
}

/// Measures how well the current frame continues history frame 0; `None`
/// when the view has no history.
pub fn scene_cut_score(view: &HistoryView<'_>, current: &PreparedFrame) -> Option<SceneCutScore> {
    if view.is_empty() {
        return None;
    }
    let lattice = Lattice::new(current.width(), current.height());
    let cur = current_samples(&lattice, current);
    let hist = history_samples(&lattice, view);
    Some(score_samples(&lattice, &cur, &hist, geometric(view)))
}

/// True when history frame 0 of `view` is aligned by depth or motion
/// vectors (so its validity is measured, not assumed).
pub fn geometric(view: &HistoryView<'_>) -> bool {
    matches!(
        view.mode(0),
        ReprojectionMode::MotionVectors | ReprojectionMode::DepthCamera
    )
}

/// The score from the samples at `lattice` of the current frame (`cur`:
/// RGB premultiplied, coverage; see [`current_samples`]) and of history
/// frame 0 reprojected (`hist`: RGB, validity; see [`history_samples`]);
/// `geometric` as [`geometric`] says. The same sums in the same order
/// whichever pass took the samples, so the same score bit for bit.
///
/// # Panics
/// When a slice does not hold one sample per lattice pixel.
pub fn score_samples(
    lattice: &Lattice,
    cur: &[[f32; 4]],
    hist: &[[f32; 4]],
    geometric: bool,
) -> SceneCutScore {
    assert_eq!(cur.len(), lattice.len(), "current samples");
    assert_eq!(hist.len(), lattice.len(), "history samples");
    let s = lattice.cell;
    let (gw, gh) = (lattice.width.div_ceil(s), lattice.height.div_ceil(s));
    let nx = lattice.columns.len();
    let mut cells = vec![Cell::default(); gw * gh];
    for (r, &y) in lattice.rows.iter().enumerate() {
        let row = &mut cells[(y / s) * gw..(y / s + 1) * gw];
        let (cr, hr) = (&cur[r * nx..(r + 1) * nx], &hist[r * nx..(r + 1) * nx]);
        for ((&x, c), h) in lattice.columns.iter().zip(cr).zip(hr) {
            let cell = &mut row[x / s];
            cell.area += 1.0;
            let v = h[3];
            if v <= 0.0 {
                continue;
            }
            let cv = c[3];
            cell.weight += v * cv;
            for ch in 0..3 {
                cell.cur[ch] += v * c[ch];
                cell.hist[ch] += v * cv * h[ch];
            }
        }
    }
    let cells: Vec<Cell> = cells
        .into_iter()
        .filter(|c| c.area > 0.0 && c.weight >= 0.5 * c.area)
        .collect();
    let total = gw * gh;
    if cells.is_empty() {
        return SceneCutScore {
            cells: total,
            compared: 0,
            mismatch: 0.0,
            exposure_offset: 0.0,
            geometric,
        };
    }
    let lum = |c: &[f32; 3]| 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
    let mean_lum = cells.iter().map(|c| lum(&c.cur) / c.weight).sum::<f32>() / cells.len() as f32;
    let eps = 1e-4 + 1e-2 * mean_lum;
    let chroma = |c: &[f32; 3], wt: f32| {
        let s = c[0] + c[1] + c[2] + 3.0 * eps * wt;
        [c[0] / s, c[1] / s]
    };
    let diffs: Vec<(f32, f32)> = cells
        .iter()
        .map(|c| {
            let lc = lum(&c.cur) / c.weight + eps;
            let lh = lum(&c.hist) / c.weight + eps;
            let cc = chroma(&c.cur, c.weight);
            let ch = chroma(&c.hist, c.weight);
            (
                (lc / lh).ln(),
                (cc[0] - ch[0]).abs() + (cc[1] - ch[1]).abs(),
            )
        })
        .collect();
    let mut logs: Vec<f32> = diffs.iter().map(|d| d.0).collect();
    logs.sort_by(f32::total_cmp);
    let offset = logs[logs.len() / 2];
    let bad = diffs
        .iter()
        .filter(|(l, c)| (l - offset).abs() > LOG_TOLERANCE || *c > CHROMA_TOLERANCE)
        .count();
    SceneCutScore {
        cells: total,
        compared: cells.len(),
        mismatch: bad as f32 / cells.len() as f32,
        exposure_offset: offset,
        geometric,
    }
}

/// True when the current frame does not continue the history (a cut).
/// `threshold` is the fraction of compared cells that must mismatch.
pub fn is_scene_cut(view: &HistoryView<'_>, current: &PreparedFrame, threshold: f32) -> bool {
    scene_cut_score(view, current).is_some_and(|s| s.is_cut(threshold))
}
