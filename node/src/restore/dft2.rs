//! The 2-D DFT of a real image, for the Wiener deconvolution ([`super::psf`]).
//!
//! Each row's real DFT (realfft: its `cols/2 + 1` non-negative
//! frequencies), then the complex DFT of each of those half-spectrum
//! columns (rustfft, all in one call). The half spectrum is kept column by
//! column: frequency `(u, v)` (row `u`, column `v ≤ cols/2`) at
//! `v·rows + u`, the order the column DFTs run in; the inverse runs the
//! same steps backwards and is unscaled (`rows·cols` times the image).
//! On the sizes the deconvolution uses (96² to 576x864) a forward and
//! inverse pair takes a third of OpenCV 4.6's `dft` pair (`docs/restoration.md`).

use super::RestoreError;
use realfft::num_complex::Complex32;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::{Fft, FftPlanner};
use std::sync::Arc;

/// Plans of every size asked so far (each size's plan is made once).
pub(crate) struct Dft2Planner {
    real: RealFftPlanner<f32>,
    complex: FftPlanner<f32>,
}

impl Default for Dft2Planner {
    fn default() -> Self {
        Self {
            real: RealFftPlanner::new(),
            complex: FftPlanner::new(),
        }
    }
}

impl std::fmt::Debug for Dft2Planner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Dft2Planner")
    }
}

impl Dft2Planner {
    /// The DFT of a `rows`x`cols` image (both ≥ 1).
    pub(crate) fn plan(&mut self, rows: usize, cols: usize) -> Dft2 {
        Dft2 {
            rows,
            cols,
            r2c: self.real.plan_fft_forward(cols),
            c2r: self.real.plan_fft_inverse(cols),
            fwd: self.complex.plan_fft_forward(rows),
            inv: self.complex.plan_fft_inverse(rows),
        }
    }
}

/// Buffers a [`Dft2`] works in, kept between calls (grown, never shrunk).
#[derive(Debug, Default)]
pub(crate) struct Dft2Work {
    /// The rows' half spectra, row by row.
    rows: Vec<Complex32>,
    scratch: Vec<Complex32>,
}

/// The 2-D DFT of one size ([`Dft2Planner::plan`]).
pub(crate) struct Dft2 {
    rows: usize,
    cols: usize,
    r2c: Arc<dyn RealToComplex<f32>>,
    c2r: Arc<dyn ComplexToReal<f32>>,
    fwd: Arc<dyn Fft<f32>>,
    inv: Arc<dyn Fft<f32>>,
}

impl Dft2 {
    pub(crate) fn rows(&self) -> usize {
        self.rows
    }

    pub(crate) fn cols(&self) -> usize {
        self.cols
    }

    /// Columns of the half spectrum: `cols/2 + 1`.
    pub(crate) fn half(&self) -> usize {
        self.cols / 2 + 1
    }

    /// Length of the half spectrum: `half()·rows`.
    pub(crate) fn spectrum_len(&self) -> usize {
        self.half() * self.rows
    }

    fn check(&self, image: usize, spectrum: usize) -> Result<(), RestoreError> {
        if image != self.rows * self.cols || spectrum != self.spectrum_len() {
            return Err(self.error(format!(
                "{image} pixels and {spectrum} frequencies given, {} and {} needed",
                self.rows * self.cols,
                self.spectrum_len()
            )));
        }
        Ok(())
    }

    fn error(&self, reason: String) -> RestoreError {
        RestoreError::Dft {
            rows: self.rows,
            cols: self.cols,
            reason,
        }
    }

    /// Sizes the work buffers for this DFT; returns the rows' buffer and the scratch.
    fn buffers<'w>(&self, work: &'w mut Dft2Work) -> (&'w mut [Complex32], &'w mut [Complex32]) {
        let scratch = [
            self.r2c.get_scratch_len(),
            self.c2r.get_scratch_len(),
            self.fwd.get_inplace_scratch_len(),
            self.inv.get_inplace_scratch_len(),
        ]
        .into_iter()
        .max()
        .unwrap_or(0);
        let n = self.spectrum_len();
        if work.rows.len() < n {
            work.rows.resize(n, Complex32::default());
        }
        if work.scratch.len() < scratch {
            work.scratch.resize(scratch, Complex32::default());
        }
        (&mut work.rows[..n], &mut work.scratch[..scratch])
    }

    /// The half spectrum of `image` (`rows`x`cols`, row-major; used as
    /// scratch) into `spectrum` (column by column, see the module).
    pub(crate) fn forward(
        &self,
        image: &mut [f32],
        spectrum: &mut [Complex32],
        work: &mut Dft2Work,
    ) -> Result<(), RestoreError> {
        self.check(image.len(), spectrum.len())?;
        let half = self.half();
        let (by_rows, scratch) = self.buffers(work);
        for (row, out) in image
            .chunks_exact_mut(self.cols)
            .zip(by_rows.chunks_exact_mut(half))
        {
            self.r2c
                .process_with_scratch(row, out, scratch)
                .map_err(|e| self.error(e.to_string()))?;
        }
        transpose::transpose(by_rows, spectrum, half, self.rows);
        self.fwd.process_with_scratch(spectrum, scratch);
        Ok(())
    }

    /// The image of the half spectrum `spectrum` (used as scratch) into
    /// `image`, times `rows·cols`. The imaginary parts that a real image's
    /// spectrum does not have (each row's frequency 0, and `cols/2` for an
    /// even width) are dropped.
    pub(crate) fn inverse(
        &self,
        spectrum: &mut [Complex32],
        image: &mut [f32],
        work: &mut Dft2Work,
    ) -> Result<(), RestoreError> {
        self.check(image.len(), spectrum.len())?;
        let half = self.half();
        let (by_rows, scratch) = self.buffers(work);
        self.inv.process_with_scratch(spectrum, scratch);
        transpose::transpose(spectrum, by_rows, self.rows, half);
        for (row, out) in by_rows
            .chunks_exact_mut(half)
            .zip(image.chunks_exact_mut(self.cols))
        {
            row[0].im = 0.0;
            if self.cols.is_multiple_of(2) {
                row[half - 1].im = 0.0;
            }
            self.c2r
                .process_with_scratch(row, out, scratch)
                .map_err(|e| self.error(e.to_string()))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{self, Mat, Vec2f, DFT_COMPLEX_OUTPUT};
    use opencv::prelude::*;
    use rand::{Rng, SeedableRng};

    fn random_image(rows: usize, cols: usize, seed: u64) -> Vec<f32> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..rows * cols)
            .map(|_| rng.gen_range(-128.0f32..128.0))
            .collect()
    }

    #[test]
    fn the_half_spectrum_is_opencvs_complex_dft() {
        let mut planner = Dft2Planner::default();
        let mut work = Dft2Work::default();
        // Even and odd sides, sizes the deconvolution uses, primes.
        for (i, (rows, cols)) in [
            (96, 96),
            (160, 192),
            (45, 63),
            (33, 40),
            (40, 33),
            (7, 1),
            (1, 9),
            (31, 17),
        ]
        .into_iter()
        .enumerate()
        {
            let image = random_image(rows, cols, i as u64);
            let m = Mat::new_rows_cols_with_data(rows as i32, cols as i32, &image)
                .unwrap()
                .try_clone()
                .unwrap();
            let mut reference = Mat::default();
            core::dft(&m, &mut reference, DFT_COMPLEX_OUTPUT, 0).unwrap();
            let dft = planner.plan(rows, cols);
            let mut spectrum = vec![Complex32::default(); dft.spectrum_len()];
            dft.forward(&mut image.clone(), &mut spectrum, &mut work)
                .unwrap();
            let scale = (rows * cols) as f32 * 128.0;
            for u in 0..rows {
                let row = reference.at_row::<Vec2f>(u as i32).unwrap();
                for v in 0..dft.half() {
                    let (want, got) = (row[v], spectrum[v * rows + u]);
                    assert!(
                        (want[0] - got.re).abs() < 2e-6 * scale
                            && (want[1] - got.im).abs() < 2e-6 * scale,
                        "{rows}x{cols} at ({u}, {v}): OpenCV {want:?}, ours {got}"
                    );
                }
            }
            // And back, times rows·cols.
            let mut back = vec![0f32; rows * cols];
            dft.inverse(&mut spectrum, &mut back, &mut work).unwrap();
            let n = (rows * cols) as f32;
            for (a, b) in back.iter().zip(&image) {
                assert!(
                    (a / n - b).abs() < 1e-3,
                    "{rows}x{cols}: {} back as {}",
                    b,
                    a / n
                );
            }
        }
    }

    #[test]
    fn buffers_of_the_wrong_size_are_an_error_not_a_panic() {
        let dft = Dft2Planner::default().plan(8, 6);
        let mut work = Dft2Work::default();
        let mut spectrum = vec![Complex32::default(); dft.spectrum_len()];
        let err = dft
            .forward(&mut [0.0; 47], &mut spectrum, &mut work)
            .unwrap_err();
        assert!(
            err.to_string().contains("8x6") && err.to_string().contains("47 pixels"),
            "{err}"
        );
        assert!(dft
            .inverse(&mut spectrum[1..], &mut [0.0; 48], &mut work)
            .is_err());
    }
}
