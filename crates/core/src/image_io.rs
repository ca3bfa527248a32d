//! Images in and out: linear RGB float EXR, and a tone-mapped sRGB PNG
//! preview.

use std::path::Path;

/// A linear RGB float image, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[f32; 3]>,
}

#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("{file}: {message}")]
    Exr { file: String, message: String },
    #[error("{file}: {message}")]
    Png { file: String, message: String },
    #[error("images differ in size: {a:?} and {b:?}")]
    SizeMismatch { a: (u32, u32), b: (u32, u32) },
}

impl Image {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: vec![[0.0; 3]; width as usize * height as usize],
        }
    }

    pub fn write_exr(&self, path: &Path) -> Result<(), ImageError> {
        let w = self.width as usize;
        exr::prelude::write_rgb_file(path, w, self.height as usize, |x, y| {
            let p = self.pixels[y * w + x];
            (p[0], p[1], p[2])
        })
        .map_err(|e| ImageError::Exr {
            file: path.display().to_string(),
            message: e.to_string(),
        })
    }

    pub fn read_exr(path: &Path) -> Result<Image, ImageError> {
        let img = exr::prelude::read_first_rgba_layer_from_file(
            path,
            |res, _| Image::new(res.0 as u32, res.1 as u32),
            |img: &mut Image, pos, (r, g, b, _a): (f32, f32, f32, f32)| {
                let i = pos.1 * img.width as usize + pos.0;
                img.pixels[i] = [r, g, b];
            },
        )
        .map_err(|e| ImageError::Exr {
            file: path.display().to_string(),
            message: e.to_string(),
        })?;
        Ok(img.layer_data.channel_data.pixels)
    }

    /// An 8-bit sRGB preview: linear values times `exposure`, clipped to
    /// [0, 1], then the sRGB transfer curve.
    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<(), ImageError> {
        let buf = self.to_srgb8(exposure);
        image::save_buffer(path, &buf, self.width, self.height, image::ColorType::Rgb8).map_err(
            |e| ImageError::Png {
                file: path.display().to_string(),
                message: e.to_string(),
            },
        )
    }

    /// The same preview as [`Image::write_png`], as PNG bytes in memory
    /// (the scheduler's live preview).
    pub fn encode_png(&self, exposure: f32) -> Result<Vec<u8>, ImageError> {
        let buf = self.to_srgb8(exposure);
        let mut out = std::io::Cursor::new(Vec::new());
        image::write_buffer_with_format(
            &mut out,
            &buf,
            self.width,
            self.height,
            image::ColorType::Rgb8,
            image::ImageFormat::Png,
        )
        .map_err(|e| ImageError::Png {
            file: "(preview)".into(),
            message: e.to_string(),
        })?;
        Ok(out.into_inner())
    }

    fn to_srgb8(&self, exposure: f32) -> Vec<u8> {
        let mut buf = Vec::with_capacity(self.pixels.len() * 3);
        for p in &self.pixels {
            for c in p {
                buf.push((srgb_oetf((c * exposure).clamp(0.0, 1.0)) * 255.0 + 0.5) as u8);
            }
        }
        buf
    }

    /// Mean of each channel.
    pub fn mean(&self) -> [f64; 3] {
        let mut s = [0f64; 3];
        for p in &self.pixels {
            for c in 0..3 {
                s[c] += p[c] as f64;
            }
        }
        let n = self.pixels.len().max(1) as f64;
        [s[0] / n, s[1] / n, s[2] / n]
    }

    pub fn to_bits(&self) -> Vec<u32> {
        self.pixels
            .iter()
            .flat_map(|p| p.map(f32::to_bits))
            .collect()
    }
}

fn srgb_oetf(x: f32) -> f32 {
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}
