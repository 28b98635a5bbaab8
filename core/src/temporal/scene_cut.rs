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

/// Measures how well the current frame continues history frame 0; `None`
/// when the view has no history.
pub fn scene_cut_score(view: &HistoryView<'_>, current: &PreparedFrame) -> Option<SceneCutScore> {
    if view.is_empty() {
        return None;
    }
    let geometric = matches!(
        view.mode(0),
        ReprojectionMode::MotionVectors | ReprojectionMode::DepthCamera
    );
    let (w, h) = (current.width(), current.height());
    let s = (w.max(h).div_ceil(64)).max(8);
    let (gw, gh) = (w.div_ceil(s), h.div_ceil(s));
    // A sparse lattice of pixels, about 4 x 4 per cell: only those are
    // reprojected (cheap when history frame 0 was not reprojected yet).
    let step = (s / 4).max(1);
    let n = w * h;
    let cov = current.coverage.as_deref();
    let cur = &current.color.data;
    let at = view.sampler(0);
    let row_cells = |gy: usize| -> Vec<Cell> {
        let mut cells = vec![Cell::default(); gw];
        for y in (gy * s + step / 2..((gy + 1) * s).min(h)).step_by(step) {
            for (gx, cell) in cells.iter_mut().enumerate() {
                for x in (gx * s + step / 2..((gx + 1) * s).min(w)).step_by(step) {
                    let p = y * w + x;
                    cell.area += 1.0;
                    let (hist, v) = at.at(y, x);
                    if v <= 0.0 {
                        continue;
                    }
                    let c = cov.map_or(1.0, |c| c[p]);
                    cell.weight += v * c;
                    for ch in 0..3 {
                        cell.cur[ch] += v * cur[ch * n + p];
                        cell.hist[ch] += v * c * hist[ch];
                    }
                }
            }
        }
        cells
    };
    let rows: Vec<Vec<Cell>> = match view.pool() {
        Some(pool) => pool.install(|| (0..gh).into_par_iter().map(row_cells).collect()),
        None => (0..gh).map(row_cells).collect(),
    };
    let cells: Vec<Cell> = rows
        .into_iter()
        .flatten()
        .filter(|c| c.area > 0.0 && c.weight >= 0.5 * c.area)
        .collect();
    let total = gw * gh;
    if cells.is_empty() {
        return Some(SceneCutScore {
            cells: total,
            compared: 0,
            mismatch: 0.0,
            exposure_offset: 0.0,
            geometric,
        });
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
    Some(SceneCutScore {
        cells: total,
        compared: cells.len(),
        mismatch: bad as f32 / cells.len() as f32,
        exposure_offset: offset,
        geometric,
    })
}

/// True when the current frame does not continue the history (a cut).
/// `threshold` is the fraction of compared cells that must mismatch.
pub fn is_scene_cut(view: &HistoryView<'_>, current: &PreparedFrame, threshold: f32) -> bool {
    scene_cut_score(view, current).is_some_and(|s| s.is_cut(threshold))
}
