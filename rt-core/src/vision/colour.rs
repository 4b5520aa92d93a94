//! The ball's colour test, one pass per search region.
//!
//! The detector's colour rule is OpenCV's 8-bit `COLOR_BGR2HSV` (hue in half
//! degrees 0..180, saturation and value 0..255) followed by `in_range`. OpenCV
//! computes the hue of every pixel in floating-point-free but branchy code and
//! writes a three-channel image, then reads it again: at 1280x720 the two were
//! half of a full-frame search (1.0 ms and 0.27 ms of 2.6 ms at half
//! resolution on this workplace's VM). [`HsvRange::mask`] applies the same rule in
//! one pass: value first, saturation next, the hue only for the pixels that pass
//! both (most of a scene is too dark or too grey for the ball). It uses OpenCV's
//! own integer tables and rounding (`hsv_shift` 12), so the mask is the same bit
//! for bit: the tests compare it with `cvt_color` + `in_range` on all 2^24
//! colours.

use opencv::core::{self, Mat, MatTraitConst, MatTraitConstManual, MatTraitManual, Scalar, Vec3b};

use super::{FrameProblem, VisionError};

/// OpenCV's fixed-point shift of the 8-bit HSV conversion.
const HSV_SHIFT: u32 = 12;
const HALF: i32 = 1 << (HSV_SHIFT - 1);

/// An inclusive range of 8-bit HSV (OpenCV's scale: hue 0..180) and OpenCV's
/// division tables.
#[derive(Clone)]
pub struct HsvRange {
    lo: [i32; 3],
    hi: [i32; 3],
    /// `round(255 * 2^12 / i)` (0 for 0): saturation = diff / value.
    sdiv: [i32; 256],
    /// `round(180 * 2^12 / (6 i))` (0 for 0): hue = difference / diff, in
    /// half degrees.
    hdiv: [i32; 256],
    /// Per value v: the saturation is in range exactly for max - min in
    /// `dmin[v]..=dmax[v]` (saturation grows with max - min), so the test
    /// needs no division, no rounding and no branch per pixel.
    dmin: [i32; 256],
    dmax: [i32; 256],
}

impl std::fmt::Debug for HsvRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HsvRange")
            .field("lo", &self.lo)
            .field("hi", &self.hi)
            .finish_non_exhaustive()
    }
}

impl HsvRange {
    /// The range `lo..=hi` per channel (hue, saturation, value).
    pub fn new(lo: [u8; 3], hi: [u8; 3]) -> Self {
        let mut sdiv = [0; 256];
        let mut hdiv = [0; 256];
        for i in 1..256 {
            // OpenCV's saturate_cast<int>(double): round half to even.
            sdiv[i] = (f64::from(255 << HSV_SHIFT) / i as f64).round_ties_even() as i32;
            hdiv[i] = (f64::from(180 << HSV_SHIFT) / (6.0 * i as f64)).round_ties_even() as i32;
        }
        let (lo, hi) = (lo.map(i32::from), hi.map(i32::from));
        let mut dmin = [256; 256];
        let mut dmax = [-1; 256];
        for v in 0..256 {
            for diff in 0..=v as i32 {
                let s = (diff * sdiv[v] + HALF) >> HSV_SHIFT;
                if (lo[1]..=hi[1]).contains(&s) {
                    dmin[v] = dmin[v].min(diff);
                    dmax[v] = dmax[v].max(diff);
                }
            }
        }
        Self {
            lo,
            hi,
            sdiv,
            hdiv,
            dmin,
            dmax,
        }
    }

    /// OpenCV's 8-bit HSV of a BGR pixel (`COLOR_BGR2HSV`).
    pub fn hsv(&self, b: u8, g: u8, r: u8) -> [u8; 3] {
        let (b, g, r) = (i32::from(b), i32::from(g), i32::from(r));
        let v = b.max(g).max(r);
        let diff = v - b.min(g).min(r);
        let s = (diff * self.sdiv[v as usize] + HALF) >> HSV_SHIFT;
        [self.hue(b, g, r, v, diff) as u8, s as u8, v as u8]
    }

    /// The hue in half degrees, 0..=180 (OpenCV's formula and rounding).
    #[inline(always)]
    fn hue(&self, b: i32, g: i32, r: i32, v: i32, diff: i32) -> i32 {
        let h = if v == r {
            g - b
        } else if v == g {
            b - r + 2 * diff
        } else {
            r - g + 4 * diff
        };
        let h = (h * self.hdiv[diff as usize] + HALF) >> HSV_SHIFT;
        let h = if h < 0 { h + 180 } else { h };
        h.clamp(0, 255)
    }

    /// Whether a BGR pixel's HSV lies in the range.
    #[inline(always)]
    pub fn contains(&self, b: u8, g: u8, r: u8) -> bool {
        let (b, g, r) = (i32::from(b), i32::from(g), i32::from(r));
        let v = b.max(g).max(r);
        let diff = v - b.min(g).min(r);
        let vi = v as usize & 255;
        // Value and saturation without branches (most pixels fail here, in
        // no predictable pattern); the hue only for those that pass.
        let sv = (v >= self.lo[2])
            && (v <= self.hi[2])
            && (diff >= self.dmin[vi])
            && (diff <= self.dmax[vi]);
        sv && {
            let h = self.hue(b, g, r, v, diff);
            h >= self.lo[0] && h <= self.hi[0]
        }
    }

    /// `out` = 255 where `img` (8-bit BGR, a view of a frame is fine) is in the
    /// range, 0 elsewhere; `out` is reallocated only when its size changes.
    ///
    /// # Errors
    ///
    /// As [`Self::mask_sampled`].
    pub fn mask(&self, img: &impl MatTraitConst, out: &mut Mat) -> Result<(), VisionError> {
        self.mask_sampled(img, 1, out)
    }

    /// [`Self::mask`] of every `step`-th pixel of every `step`-th row (the
    /// pixel at the top left of each `step` x `step` block): `out` is
    /// `rows / step` x `cols / step`, as `resize` to that size would make it.
    ///
    /// # Errors
    ///
    /// [`VisionError::BadFrame`] when `img` is not 8-bit BGR; [`VisionError::OpenCv`]
    /// when `out` cannot be allocated or a row cannot be accessed.
    pub fn mask_sampled(
        &self,
        img: &impl MatTraitConst,
        step: i32,
        out: &mut Mat,
    ) -> Result<(), VisionError> {
        let step = step.max(1);
        let (rows, cols) = (img.rows() / step, img.cols() / step);
        if img.typ() != core::CV_8UC3 {
            return Err(FrameProblem::NotBgr {
                width_px: img.cols(),
                height_px: img.rows(),
                cv_type: img.typ(),
            }
            .into());
        }
        if out.rows() != rows || out.cols() != cols || out.typ() != core::CV_8UC1 {
            *out = Mat::new_rows_cols_with_default(rows, cols, core::CV_8UC1, Scalar::all(0.0))?;
        }
        for y in 0..rows {
            let src = img.at_row::<Vec3b>(y * step)?;
            let dst = out.at_row_mut::<u8>(y)?;
            if step == 1 {
                self.mask_row(dst, src.iter());
            } else {
                self.mask_row(dst, src.iter().step_by(step as usize));
            }
        }
        Ok(())
    }

    /// One row of [`Self::mask_sampled`] (the plain iterator for step 1:
    /// `step_by` costs a fifth more per pixel).
    #[inline(always)]
    fn mask_row<'a>(&self, dst: &mut [u8], src: impl Iterator<Item = &'a Vec3b>) {
        for (d, p) in dst.iter_mut().zip(src) {
            *d = if self.contains(p[0], p[1], p[2]) {
                255
            } else {
                0
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::imgproc;

    /// Every 8-bit BGR colour once: 4096 x 4096 pixels, pixel i = (b, g, r) =
    /// (i & 255, (i >> 8) & 255, i >> 16).
    fn all_colours() -> Mat {
        let mut m =
            Mat::new_rows_cols_with_default(4096, 4096, core::CV_8UC3, Scalar::all(0.0)).unwrap();
        for y in 0..4096 {
            let row = m.at_row_mut::<Vec3b>(y).unwrap();
            for (x, p) in row.iter_mut().enumerate() {
                let i = (y as usize) * 4096 + x;
                *p = Vec3b::from([(i & 255) as u8, ((i >> 8) & 255) as u8, (i >> 16) as u8]);
            }
        }
        m
    }

    #[test]
    fn hsv_and_the_mask_equal_opencvs_on_every_colour() {
        let img = all_colours();
        let mut hsv = Mat::default();
        imgproc::cvt_color_def(&img, &mut hsv, imgproc::COLOR_BGR2HSV).unwrap();
        let any = HsvRange::new([0, 0, 0], [180, 255, 255]);
        for y in 0..4096 {
            let src = img.at_row::<Vec3b>(y).unwrap();
            let want = hsv.at_row::<Vec3b>(y).unwrap();
            for (p, w) in src.iter().zip(want) {
                assert_eq!(
                    any.hsv(p[0], p[1], p[2]),
                    [w[0], w[1], w[2]],
                    "BGR {:?}",
                    [p[0], p[1], p[2]]
                );
            }
        }
        // The detector's default range, one with its edges inside the
        // scale, the reds at hue 0, and an empty hue range.
        for (lo, hi) in [
            ([24u8, 115u8, 46u8], [50u8, 255u8, 255u8]),
            ([10, 1, 1], [170, 254, 254]),
            ([0, 100, 100], [0, 255, 255]),
            ([90, 0, 0], [89, 255, 255]),
        ] {
            let range = HsvRange::new(lo, hi);
            let mut ours = Mat::default();
            range.mask(&img, &mut ours).unwrap();
            let mut theirs = Mat::default();
            let l = Scalar::new(lo[0].into(), lo[1].into(), lo[2].into(), 0.0);
            let h = Scalar::new(hi[0].into(), hi[1].into(), hi[2].into(), 0.0);
            core::in_range(&hsv, &l, &h, &mut theirs).unwrap();
            let mut diff = Mat::default();
            core::compare(&ours, &theirs, &mut diff, core::CMP_NE).unwrap();
            assert_eq!(core::count_non_zero(&diff).unwrap(), 0, "{lo:?}..{hi:?}");
        }
    }

    #[test]
    fn a_view_of_a_frame_is_masked_in_place_and_bad_input_is_refused() {
        let img = all_colours();
        let roi = Mat::roi(&img, core::Rect::new(100, 200, 37, 11)).unwrap();
        let range = HsvRange::new([24, 115, 46], [50, 255, 255]);
        let mut out = Mat::default();
        range.mask(&roi, &mut out).unwrap();
        assert_eq!((out.rows(), out.cols(), out.typ()), (11, 37, core::CV_8UC1));
        for y in 0..11 {
            for x in 0..37 {
                let p = *roi.at_2d::<Vec3b>(y, x).unwrap();
                let want = if range.contains(p[0], p[1], p[2]) {
                    255
                } else {
                    0
                };
                assert_eq!(*out.at_2d::<u8>(y, x).unwrap(), want);
            }
        }
        // Sampled: every step-th pixel of every step-th row, the rest dropped.
        // (The second range, value <= 130, passes part of this view.)
        let dark = HsvRange::new([0, 0, 0], [180, 255, 130]);
        for (range, step) in [(&range, 2), (&range, 3), (&dark, 2), (&dark, 3)] {
            range.mask_sampled(&roi, step, &mut out).unwrap();
            assert_eq!((out.rows(), out.cols()), (11 / step, 37 / step));
            for y in 0..11 / step {
                for x in 0..37 / step {
                    let p = *roi.at_2d::<Vec3b>(y * step, x * step).unwrap();
                    let want = if range.contains(p[0], p[1], p[2]) {
                        255
                    } else {
                        0
                    };
                    assert_eq!(*out.at_2d::<u8>(y, x).unwrap(), want, "step {step}");
                }
            }
            if std::ptr::eq(range, &raw const dark) {
                let on = core::count_non_zero(&out).unwrap();
                assert!(on > 0 && on < out.rows() * out.cols(), "{on}");
            }
        }
        let grey = Mat::new_rows_cols_with_default(4, 4, core::CV_8UC1, Scalar::all(0.0)).unwrap();
        assert!(range.mask(&grey, &mut out).is_err());
    }
}
