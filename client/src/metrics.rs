//! Image metrics of `scnerf eval`, with the definitions of
//! `exporter/scnerf_export/evaluate/metrics.py` (tested on the same arrays:
//! tests/fixtures/datasets/metrics.json).

use crate::error::{Error, Result};

/// An (H, W, C) image of values in [0, 1], row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub data: Vec<f64>,
}

impl Image {
    /// 8-bit RGB(A) decoded from PNG/JPEG bytes, alpha composited on `background` as the Python
    /// loaders do (`exporter/scnerf_export/data/scene.py::read_image`).
    pub fn decode(bytes: &[u8], background: [f64; 3]) -> std::result::Result<Image, image::ImageError> {
        let rgba = image::load_from_memory(bytes)?.into_rgba32f();
        let (width, height) = (rgba.width() as usize, rgba.height() as usize);
        let mut data = Vec::with_capacity(width * height * 3);
        for px in rgba.pixels() {
            let a = f64::from(px.0[3]);
            data.extend(px.0[..3].iter().zip(background).map(|(v, bg)| f64::from(*v) * a + bg * (1.0 - a)));
        }
        Ok(Image { width, height, channels: 3, data })
    }

    /// The image box-averaged over n x n blocks
    /// (`exporter/scnerf_export/evaluate/eval.py::downscale_target`).
    pub fn downscaled(&self, n: usize) -> Image {
        let (w, h, ch) = (self.width / n, self.height / n, self.channels);
        let mut data = vec![0.0; w * h * ch];
        for y in 0..h * n {
            for x in 0..w * n {
                for c in 0..ch {
                    data[((y / n) * w + x / n) * ch + c] += self.data[(y * self.width + x) * ch + c];
                }
            }
        }
        let area = (n * n) as f64;
        data.iter_mut().for_each(|v| *v /= area);
        Image { width: w, height: h, channels: ch, data }
    }
}

/// The absolute error of `pred` against `gt`, per pixel and channel, as an 8-bit RGB PNG: where
/// the model fails, not only by how much on average.
pub fn error_png(pred: &Image, gt: &Image) -> Result<Vec<u8>> {
    same_shape(pred, gt)?;
    let bytes: Vec<u8> =
        pred.data.iter().zip(&gt.data).map(|(p, g)| ((p - g).abs().min(1.0) * 255.0).round() as u8).collect();
    let rgb = image::RgbImage::from_raw(pred.width as u32, pred.height as u32, bytes)
        .ok_or_else(|| Error::Usage("an error image needs 3 channels".into()))?;
    let mut png = Vec::new();
    rgb.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|e| Error::Usage(format!("cannot encode the error image: {e}")))?;
    Ok(png)
}

fn same_shape(pred: &Image, gt: &Image) -> Result<()> {
    if (pred.width, pred.height, pred.channels) != (gt.width, gt.height, gt.channels) {
        return Err(Error::Usage(format!(
            "rendered and ground-truth images differ in size: {}x{} vs {}x{}",
            pred.width, pred.height, gt.width, gt.height
        )));
    }
    Ok(())
}

/// 10 log10(1 / MSE) over all pixels and channels; identical images give infinity.
pub fn psnr(pred: &Image, gt: &Image) -> Result<f64> {
    same_shape(pred, gt)?;
    let mse = pred.data.iter().zip(&gt.data).map(|(p, g)| (p - g) * (p - g)).sum::<f64>() / pred.data.len() as f64;
    Ok(-10.0 * mse.log10())
}

const SSIM_WINDOW: usize = 11;
const SSIM_SIGMA: f64 = 1.5;
const SSIM_C1: f64 = 0.01 * 0.01;
const SSIM_C2: f64 = 0.03 * 0.03;

fn gaussian_window() -> [f64; SSIM_WINDOW] {
    let mid = (SSIM_WINDOW - 1) as f64 / 2.0;
    let w: [f64; SSIM_WINDOW] = std::array::from_fn(|i| (-0.5 * ((i as f64 - mid) / SSIM_SIGMA).powi(2)).exp());
    let sum: f64 = w.iter().sum();
    w.map(|v| v / sum)
}

/// Separable "valid" correlation of one channel (h x w) with the window, along rows then
/// columns: an (h - 10) x (w - 10) result (`metrics.py::_filter_valid`).
fn filter_valid(x: &[f64], w: usize, h: usize, k: &[f64; SSIM_WINDOW]) -> Vec<f64> {
    let (oh, ow) = (h - SSIM_WINDOW + 1, w - SSIM_WINDOW + 1);
    let mut rows = vec![0.0; oh * w];
    for y in 0..oh {
        for x0 in 0..w {
            rows[y * w + x0] = (0..SSIM_WINDOW).map(|i| k[i] * x[(y + i) * w + x0]).sum();
        }
    }
    let mut out = vec![0.0; oh * ow];
    for y in 0..oh {
        for x0 in 0..ow {
            out[y * ow + x0] = (0..SSIM_WINDOW).map(|i| k[i] * rows[y * w + x0 + i]).sum();
        }
    }
    out
}

/// Gaussian-window SSIM (11x11, sigma 1.5, K1 0.01, K2 0.03, data range 1) over the valid region,
/// averaged over pixels and channels, with JAX-NeRF's guards on the variances
/// (`metrics.py::ssim`).
pub fn ssim(pred: &Image, gt: &Image) -> Result<f64> {
    same_shape(pred, gt)?;
    let (w, h, ch) = (pred.width, pred.height, pred.channels);
    if w < SSIM_WINDOW || h < SSIM_WINDOW {
        return Err(Error::Usage(format!("SSIM needs images of at least 11x11, got {w}x{h}")));
    }
    let k = gaussian_window();
    let mut total = 0.0;
    let mut count = 0;
    for c in 0..ch {
        let channel = |img: &Image| -> Vec<f64> { img.data.iter().skip(c).step_by(ch).copied().collect() };
        let (p, g) = (channel(pred), channel(gt));
        let product = |a: &[f64], b: &[f64]| -> Vec<f64> { a.iter().zip(b).map(|(x, y)| x * y).collect() };
        let (mu_p, mu_g) = (filter_valid(&p, w, h, &k), filter_valid(&g, w, h, &k));
        let pp = filter_valid(&product(&p, &p), w, h, &k);
        let gg = filter_valid(&product(&g, &g), w, h, &k);
        let pg = filter_valid(&product(&p, &g), w, h, &k);
        for i in 0..mu_p.len() {
            let s_pp = (pp[i] - mu_p[i] * mu_p[i]).max(0.0);
            let s_gg = (gg[i] - mu_g[i] * mu_g[i]).max(0.0);
            let raw = pg[i] - mu_p[i] * mu_g[i];
            let s_pg = raw.signum() * (s_pp * s_gg).sqrt().min(raw.abs());
            let num = (2.0 * mu_p[i] * mu_g[i] + SSIM_C1) * (2.0 * s_pg + SSIM_C2);
            let den = (mu_p[i] * mu_p[i] + mu_g[i] * mu_g[i] + SSIM_C1) * (s_pp + s_gg + SSIM_C2);
            total += num / den;
            count += 1;
        }
    }
    Ok(total / count as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downscale_box_averages() {
        let img = Image { width: 2, height: 2, channels: 1, data: vec![0.0, 1.0, 0.5, 0.5] };
        assert_eq!(img.downscaled(2).data, vec![0.5]);
    }
}
