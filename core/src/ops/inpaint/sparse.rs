//! Push-pull evaluated only where the hole pixels need it: the values of
//! [`super::push_pull`]'s dense pyramid, bit for bit, at a cost that grows
//! with the holes and the levels they reach, not with the window.
//!
//! A pixel of level `l >= 1` has a *pulled* value (the clamped 2x2 box sum
//! of its children at level `l - 1`) and a *final* value (pulled where its
//! weight is full, else completed from the final values of level `l + 1`;
//! at a 1x1 top level, normalized). Level-0 hole pixels need the final
//! values of their four bilinear taps at level 1, which need more only
//! where those are holes too, and so on up. Both values are computed on
//! demand and memoized in tiles, with the same float operations in the
//! same order as the dense passes.

use super::{View, FULL};

/// Side of a memo tile, in pixels of its level.
const TILE: usize = 8;
const TILE_PX: usize = TILE * TILE;

/// Memo state bits.
const PULLED: u8 = 1;
const FINAL: u8 = 2;

/// The memoized values of a `TILE` x `TILE` block of one level.
struct Tile {
    pulled: [[f32; 4]; TILE_PX],
    fin: [[f32; 3]; TILE_PX],
    state: [u8; TILE_PX],
}

/// One level (1 and up): its size and which of its tiles exist.
struct Level {
    w: usize,
    h: usize,
    tiles_x: usize,
    /// Tile slot + 1 in [`Pyramid::tiles`] (0: none yet), row-major.
    index: Vec<u32>,
}

/// The lazily evaluated pyramid over a window (level 0, read-only).
pub(super) struct Pyramid<'a> {
    base: View<'a>,
    /// Level 0 read as `sqrt(A * C)` (the square root of the straight
    /// color, premultiplied: `super::push_pull_sqrt`) instead of `C`.
    sqrt: bool,
    /// Levels 1 and up (`levels[l - 1]`), the last 1x1.
    levels: Vec<Level>,
    tiles: Vec<Tile>,
}

/// The bilinear tap of fine index `x` into a coarse axis of `coarse`
/// samples, as `super::taps` computes it.
#[inline(always)]
fn tap(x: usize, coarse: usize) -> (usize, usize, f32) {
    let u = (x as f32 + 0.5) * 0.5 - 0.5;
    let u = u.clamp(0.0, (coarse - 1) as f32);
    let i0 = u.floor() as usize;
    let i1 = (i0 + 1).min(coarse - 1);
    (i0, i1, u - i0 as f32)
}

impl<'a> Pyramid<'a> {
    /// The pyramid of `base` (its levels down to 1x1; nothing computed yet).
    pub(super) fn new(base: View<'a>, sqrt: bool) -> Pyramid<'a> {
        let (mut w, mut h) = (base.width, base.height);
        let mut levels = Vec::new();
        // As the dense pyramid: at least level 1, then up to 1x1.
        loop {
            (w, h) = (w.div_ceil(2), h.div_ceil(2));
            let tiles_x = w.div_ceil(TILE);
            levels.push(Level {
                w,
                h,
                tiles_x,
                index: vec![0; tiles_x * h.div_ceil(TILE)],
            });
            if w == 1 && h == 1 {
                break;
            }
        }
        Pyramid {
            base,
            sqrt,
            levels,
            tiles: Vec::new(),
        }
    }

    /// Size of level `l` (0: the window).
    fn size(&self, l: usize) -> (usize, usize) {
        match l {
            0 => (self.base.width, self.base.height),
            _ => (self.levels[l - 1].w, self.levels[l - 1].h),
        }
    }

    /// The tile slot and the index in it of pixel (`x`, `y`) of level `l >= 1`.
    #[inline]
    fn slot(&mut self, l: usize, x: usize, y: usize) -> (usize, usize) {
        let level = &mut self.levels[l - 1];
        let t = (y / TILE) * level.tiles_x + x / TILE;
        let k = (y % TILE) * TILE + x % TILE;
        if level.index[t] == 0 {
            self.tiles.push(Tile {
                pulled: [[0.0; 4]; TILE_PX],
                fin: [[0.0; 3]; TILE_PX],
                state: [0; TILE_PX],
            });
            level.index[t] = self.tiles.len() as u32;
        }
        (level.index[t] as usize - 1, k)
    }

    /// Pixel (`x`, `y`) of level `l` as pulled (RGB premultiplied, weight).
    fn pulled(&mut self, l: usize, x: usize, y: usize) -> [f32; 4] {
        if l == 0 {
            return self.base_at(x, y);
        }
        let (s, k) = self.slot(l, x, y);
        if self.tiles[s].state[k] & PULLED != 0 {
            return self.tiles[s].pulled[k];
        }
        let (fw, fh) = self.size(l - 1);
        let (x0, y0) = (2 * x, 2 * y);
        let x1 = (x0 + 1 < fw).then_some(x0 + 1);
        let y1 = (y0 + 1 < fh).then_some(y0 + 1);
        // `super::pair_sums` of rows `y0` and `y1`: pairs across, then the rows.
        let mut row = |y: usize| -> [f32; 4] {
            let a = self.pulled(l - 1, x0, y);
            match x1 {
                Some(x1) => {
                    let b = self.pulled(l - 1, x1, y);
                    std::array::from_fn(|c| a[c] + b[c])
                }
                None => a,
            }
        };
        let top = row(y0);
        let sum = match y1 {
            Some(y1) => {
                let bottom = row(y1);
                std::array::from_fn(|c| top[c] + bottom[c])
            }
            None => top,
        };
        // `super::pull`: the weight clamped to 1, the color scaled with it.
        let wsum = sum[3];
        let wc = wsum.min(1.0);
        let kk = if wsum > 0.0 { wc / wsum } else { 0.0 };
        let a = if wsum > 0.0 { wc } else { 0.0 };
        let v = [sum[0] * kk, sum[1] * kk, sum[2] * kk, a];
        let tile = &mut self.tiles[s];
        tile.pulled[k] = v;
        tile.state[k] |= PULLED;
        v
    }

    /// Pixel (`x`, `y`) of level `l >= 1` after the push (RGB).
    fn fin(&mut self, l: usize, x: usize, y: usize) -> [f32; 3] {
        let (s, k) = self.slot(l, x, y);
        if self.tiles[s].state[k] & FINAL != 0 {
            return self.tiles[s].fin[k];
        }
        let p = self.pulled(l, x, y);
        let v = if p[3] >= FULL {
            [p[0], p[1], p[2]]
        } else if self.size(l) == (1, 1) {
            // The top level: normalized to opaque color (0 where nothing).
            let kk = if p[3] > 0.0 { 1.0 / p[3] } else { 0.0 };
            [p[0] * kk, p[1] * kk, p[2] * kk]
        } else {
            let f = self.up(l, x, y);
            let m = 1.0 - p[3];
            std::array::from_fn(|c| p[c] + m * f[c])
        };
        let tile = &mut self.tiles[s];
        tile.fin[k] = v;
        tile.state[k] |= FINAL;
        v
    }

    /// Level `l + 1`'s final color interpolated at pixel (`x`, `y`) of level
    /// `l`: down the coarse columns first, then across (`super::push_band`).
    fn up(&mut self, l: usize, x: usize, y: usize) -> [f32; 3] {
        let (cw, ch) = self.size(l + 1);
        let (i0, i1, fx) = tap(x, cw);
        let (j0, j1, fy) = tap(y, ch);
        let mut column = |i: usize| -> [f32; 3] {
            let t = self.fin(l + 1, i, j0);
            let b = self.fin(l + 1, i, j1);
            std::array::from_fn(|c| t[c] + fy * (b[c] - t[c]))
        };
        let u0 = column(i0);
        let u1 = column(i1);
        std::array::from_fn(|c| u0[c] + fx * (u1[c] - u0[c]))
    }

    /// The color a level-0 hole pixel (`x`, `y`, in the window) with weight
    /// `cov` gets: its premultiplied color plus `(1 - cov)` times the fill.
    pub(super) fn fill(&mut self, x: usize, y: usize, cov: f32) -> [f32; 3] {
        let f = self.up(0, x, y);
        let m = 1.0 - cov;
        let b = self.base_at(x, y);
        std::array::from_fn(|c| b[c] + m * f[c])
    }

    /// Level 0 at (`x`, `y`): RGB (or its square root, premultiplied, as
    /// `super::push_pull_sqrt` encodes it) and the weight.
    #[inline]
    fn base_at(&self, x: usize, y: usize) -> [f32; 4] {
        let v: [f32; 4] = std::array::from_fn(|c| self.base.row(c, y)[x]);
        if self.sqrt {
            let e = |c: usize| super::sqrt_encode(v[c], v[3]);
            [e(0), e(1), e(2), v[3]]
        } else {
            v
        }
    }
}
