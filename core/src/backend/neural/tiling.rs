//! Overlapping tiles with feathered blending.
//!
//! A frame axis that fits one window (`n <= round_up(tile, multiple)`, or
//! `n <= ` the model's static size) is one tile: its window starts at the
//! frame edge and is the axis padded on the far side by mirror reflection up
//! to a multiple of the model's `spatial_multiple` (or to the static size).
//! There are no seams, so no overlap context is added: the network sees the
//! frame as it saw whole frames in training.
//!
//! Otherwise the axis is cut into `n` cores (consecutive, nearly equal,
//! non-overlapping ranges). A tile's network window is its core widened by
//! `overlap` on both sides (reflected at the image border) and then padded on
//! the far side, again by reflection, up to the window size (a multiple of
//! `spatial_multiple`). A tile's output is kept over its core widened by
//! `f = overlap / 2`, with linear ramps across `[edge - f, edge + f)` at
//! interior edges so the weights of neighbours sum to 1. The outer
//! `overlap - f` pixels of every window are never kept: when that is at least
//! the model's receptive radius, tiled output equals the output of one window
//! over the whole frame widened by `overlap` on every side by reflection.

use crate::error::{Error, Result};

/// Tiling along one axis.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AxisPlan {
    /// Core ranges `[start, end)`, in order, covering the axis.
    pub cores: Vec<(usize, usize)>,
    /// Network window length (the same for every tile on this axis).
    pub window: usize,
    /// Context pixels before each core in its window: the overlap, or 0 for a
    /// single tile (whose window starts at the frame edge).
    pub lead: usize,
}

/// Rounds `v` up to a multiple of `m`.
pub fn round_up(v: usize, m: usize) -> usize {
    v.div_ceil(m) * m
}

impl AxisPlan {
    /// Plans an axis of `n` pixels for windows of at most `tile` pixels
    /// (`fixed`: the model's static size, which the window must equal).
    pub fn new(
        n: usize,
        tile: usize,
        overlap: usize,
        multiple: usize,
        fixed: Option<usize>,
    ) -> Result<AxisPlan> {
        let multiple = multiple.max(1);
        let tile = fixed.unwrap_or(tile);
        let largest = fixed.unwrap_or_else(|| round_up(tile, multiple));
        if n <= largest {
            let window = fixed.unwrap_or_else(|| round_up(n, multiple));
            return Ok(AxisPlan {
                cores: vec![(0, n)],
                window,
                lead: 0,
            });
        }
        let f = overlap / 2;
        let core = tile.saturating_sub(2 * overlap);
        if core == 0 {
            return Err(Error::invalid(format!(
                "tile_size {tile}: leaves no pixels inside an overlap of {overlap} on both sides"
            )));
        }
        let count = n.div_ceil(core);
        let cores: Vec<(usize, usize)> = (0..count)
            .map(|i| (i * n / count, (i + 1) * n / count))
            .collect();
        let narrowest = cores.iter().map(|c| c.1 - c.0).min().unwrap_or(0);
        if narrowest < 2 * f.max(1) {
            return Err(Error::invalid(format!(
                "tile_size {tile} with tile_overlap {overlap}: tiles keep only {narrowest} px between their \
                 feathered edges, fewer than the {} px the feathering needs; use tile_size >= {}",
                2 * f.max(1),
                4 * overlap + 2
            )));
        }
        let widest = cores.iter().map(|c| c.1 - c.0).max().unwrap_or(0);
        let window = fixed.unwrap_or_else(|| round_up(widest + 2 * overlap, multiple));
        debug_assert!(window >= widest + 2 * overlap);
        Ok(AxisPlan {
            cores,
            window,
            lead: overlap,
        })
    }

    /// Blending weight of tile `i` at pixel `p` (0 outside its kept range).
    pub fn weight(&self, i: usize, p: usize, overlap: usize) -> f32 {
        let f = overlap / 2;
        let (a, b) = self.cores[i];
        let ramp = |edge: usize| -> f32 {
            // Rises from 0 at edge - f to 1 at edge + f (a step at `edge` when f = 0).
            if f == 0 {
                return if p >= edge { 1.0 } else { 0.0 };
            }
            let t = (p as f32 + 0.5 - (edge as f32 - f as f32)) / (2 * f) as f32;
            t.clamp(0.0, 1.0)
        };
        let mut w = 1.0;
        if i > 0 {
            w *= ramp(a);
        }
        if i + 1 < self.cores.len() {
            w *= 1.0 - ramp(b);
        }
        w
    }

    /// The pixel range tile `i` contributes to (where its weight may be > 0).
    pub fn kept(&self, i: usize, overlap: usize, n: usize) -> (usize, usize) {
        let f = overlap / 2;
        let (a, b) = self.cores[i];
        (a.saturating_sub(f), (b + f).min(n))
    }
}

/// Checks that [`AxisPlan::new`] plans an axis of every length with these
/// settings, else says why (its message).
///
/// An axis longer than the largest window `L` (`round_up(tile, multiple)`,
/// or `fixed`) is cut into `k = ceil(n / core)` cores, `core = tile - 2 *
/// overlap`, the narrowest `floor(n / k)` wide, which must be at least `2 *
/// max(overlap / 2, 1)` for the feathering. So `core` must be above 0, and
/// over all `n > L` the narrowest core is smallest at the first length of
/// some `k`: for the `k` of `n = L + 1` at `L + 1`, for every later `k` at
/// `core * (k - 1) + 1`, where `floor((core * (k - 1) + 1) / k)` grows with
/// `k`. Planning those two lengths decides all.
pub fn check_settings(
    tile: usize,
    overlap: usize,
    multiple: usize,
    fixed: Option<usize>,
) -> Result<()> {
    let t = fixed.unwrap_or(tile);
    let largest = fixed.unwrap_or_else(|| round_up(t, multiple.max(1)));
    let core = t.saturating_sub(2 * overlap);
    let first = largest + 1;
    AxisPlan::new(first, tile, overlap, multiple, fixed)?;
    if core > 0 {
        let next = core * first.div_ceil(core) + 1;
        AxisPlan::new(next, tile, overlap, multiple, fixed)?;
    }
    Ok(())
}

/// The smallest tile size up to 8192 (the parameter's range) that plans
/// every axis length with `overlap` ([`check_settings`]), if any.
pub fn smallest_tile(overlap: usize, multiple: usize) -> Option<usize> {
    (1..=8192).find(|&t| check_settings(t, overlap, multiple, None).is_ok())
}

/// Index into `0..n` with mirror reflection at both ends (`-1 -> 1`, `n -> n - 2`).
pub fn reflect(i: isize, n: usize) -> usize {
    if n <= 1 {
        return 0;
    }
    let period = 2 * (n as isize - 1);
    let m = i.rem_euclid(period);
    if m < n as isize {
        m as usize
    } else {
        (period - m) as usize
    }
}

/// A frame's tiling.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TilePlan {
    /// Frame width.
    pub width: usize,
    /// Frame height.
    pub height: usize,
    /// Overlap in pixels.
    pub overlap: usize,
    /// Horizontal axis.
    pub x: AxisPlan,
    /// Vertical axis.
    pub y: AxisPlan,
}

/// One tile of a [`TilePlan`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tile {
    /// Column index of the tile.
    pub ix: usize,
    /// Row index of the tile.
    pub iy: usize,
    /// Window origin in frame pixels (negative: reflected context).
    pub origin: (isize, isize),
    /// Window size (width, height).
    pub size: (usize, usize),
}

impl TilePlan {
    /// Plans a `width` x `height` frame for windows up to `tile` pixels square.
    pub fn new(
        width: usize,
        height: usize,
        tile: usize,
        overlap: usize,
        multiple: usize,
        fixed: (Option<usize>, Option<usize>),
    ) -> Result<TilePlan> {
        Ok(TilePlan {
            width,
            height,
            overlap,
            x: AxisPlan::new(width, tile, overlap, multiple, fixed.0)?,
            y: AxisPlan::new(height, tile, overlap, multiple, fixed.1)?,
        })
    }

    /// Number of tiles.
    pub fn len(&self) -> usize {
        self.x.cores.len() * self.y.cores.len()
    }

    /// True when the plan has no tiles (never for a non-empty frame).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Window pixels per tile.
    pub fn window_pixels(&self) -> usize {
        self.x.window * self.y.window
    }

    /// The tiles in row-major order.
    pub fn tiles(&self) -> impl Iterator<Item = Tile> + '_ {
        let (lx, ly) = (self.x.lead as isize, self.y.lead as isize);
        (0..self.y.cores.len()).flat_map(move |iy| {
            (0..self.x.cores.len()).map(move |ix| Tile {
                ix,
                iy,
                origin: (
                    self.x.cores[ix].0 as isize - lx,
                    self.y.cores[iy].0 as isize - ly,
                ),
                size: (self.x.window, self.y.window),
            })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflect_mirrors() {
        let got: Vec<usize> = (-3..8).map(|i| reflect(i, 5)).collect();
        assert_eq!(got, vec![3, 2, 1, 0, 1, 2, 3, 4, 3, 2, 1]);
        assert_eq!(reflect(-7, 1), 0);
    }

    #[test]
    fn one_window_when_the_axis_fits() {
        let p = AxisPlan::new(576, 1280, 62, 16, None).unwrap();
        assert_eq!(
            (p.cores.clone(), p.window, p.lead),
            (vec![(0, 576)], 576, 0)
        );
        let p = AxisPlan::new(570, 576, 62, 16, None).unwrap();
        assert_eq!(
            (p.cores.clone(), p.window, p.lead),
            (vec![(0, 570)], 576, 0)
        );
        let p = AxisPlan::new(200, 64, 8, 16, Some(256)).unwrap();
        assert_eq!(
            (p.cores.clone(), p.window, p.lead),
            (vec![(0, 200)], 256, 0)
        );
        let p = AxisPlan::new(577, 576, 62, 16, None).unwrap();
        assert_eq!((p.cores.len(), p.lead), (2, 62));
        let plan = TilePlan::new(1024, 576, 1024, 62, 16, (None, None)).unwrap();
        let tiles: Vec<Tile> = plan.tiles().collect();
        assert_eq!(tiles.len(), 1);
        assert_eq!((tiles[0].origin, tiles[0].size), ((0, 0), (1024, 576)));
    }

    /// Regression (issue 12): settings that passed commit but failed every
    /// frame wider than a tile. `check_settings` agrees with planning every
    /// axis length up to several tiles.
    #[test]
    fn check_settings_agrees_with_planning_every_length() {
        for multiple in [1, 8, 16] {
            for overlap in [0, 1, 2, 3, 5, 8, 16] {
                for tile in 1..=80 {
                    let every = (1..=6 * tile + 40)
                        .all(|n| AxisPlan::new(n, tile, overlap, multiple, None).is_ok());
                    let checked = check_settings(tile, overlap, multiple, None).is_ok();
                    assert_eq!(
                        checked, every,
                        "tile {tile} overlap {overlap} multiple {multiple}"
                    );
                }
            }
        }
        for (tile, overlap) in [(32, 16), (1, 0), (1, 8), (64, 64)] {
            assert!(check_settings(tile, overlap, 16, None).is_err());
        }
        assert!(check_settings(64, 8, 16, None).is_ok());
        assert_eq!(smallest_tile(16, 1), Some(53));
    }

    #[test]
    fn weights_partition_unity() {
        for (n, tile, overlap) in [
            (333, 64, 8),
            (187, 48, 6),
            (100, 40, 9),
            (50, 256, 8),
            (77, 20, 0),
            (64, 64, 8),
            (65, 64, 8),
            (80, 64, 8),
            (81, 64, 8),
        ] {
            let p = AxisPlan::new(n, tile, overlap, 16, None).unwrap();
            assert!(p.window <= round_up(tile, 16));
            assert_eq!(p.window % 16, 0);
            let single = p.cores.len() == 1;
            assert_eq!(single, n <= round_up(tile, 16), "n {n} tile {tile}");
            assert_eq!(p.lead, if single { 0 } else { overlap });
            for x in 0..n {
                let s: f32 = (0..p.cores.len()).map(|i| p.weight(i, x, overlap)).sum();
                assert!((s - 1.0).abs() < 1e-6, "n {n} tile {tile} x {x}: {s}");
                for i in 0..p.cores.len() {
                    let (a, b) = p.kept(i, overlap, n);
                    if p.weight(i, x, overlap) > 0.0 && !single {
                        assert!(x >= a && x < b);
                        let (c0, c1) = p.cores[i];
                        // Guard: kept pixels are at least overlap - f from the window edge.
                        let o = overlap as isize;
                        let lo = c0 as isize - o;
                        let hi = c1 as isize + o;
                        let g = (overlap - overlap / 2) as isize;
                        assert!(x as isize >= lo + g && (x as isize) < hi - g);
                    }
                }
            }
        }
    }
}
