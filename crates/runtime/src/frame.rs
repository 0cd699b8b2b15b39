//! Camera frames as the model sees them: RGB, 8 bits, S x S.
//!
//! Compressed images (JPEG or PNG, from `/head_camera/image_raw/compressed`
//! or a recording) enter through [`decode_compressed`]; raw RGB from the
//! camera enters through [`Frame::from_rgb`] + [`resize_area`]. Every frame
//! is brought to the model's size once, on arrival, by the ONE resize method
//! of this crate, [`resize_area`] (area average, see there), so that live,
//! replay and training frames are the same bytes. Frames leave as `u8` HWC
//! and, for the network, as `f32` planes in `[0, 1]` ([`Frame::write_chw`]).
//! Training and evaluation keep a recording's frames compressed
//! ([`CompressedFrame`]: checked to decode once, decoded again when a
//! window is built); the daemon decodes each frame once, on arrival.

use image::ImageFormat;

/// Why a frame could not be made.
#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    #[error("unsupported image format {format:?} (expected jpeg or png)")]
    UnsupportedFormat { format: String },
    #[error("cannot decode {format} image of {len} bytes: {reason}")]
    Decode {
        format: &'static str,
        len: usize,
        reason: String,
    },
    #[error("frame buffer has {len} bytes, expected {width} x {height} x 3 = {expected}")]
    BadBuffer {
        width: u32,
        height: u32,
        len: usize,
        expected: usize,
    },
    #[error("frame size must be at least 1 x 1 (got {width} x {height})")]
    Empty { width: u32, height: u32 },
}

/// An RGB image, 8 bits per channel, HWC (row-major, 3 bytes per pixel).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

impl Frame {
    /// Wrap an RGB buffer, checking its length.
    pub fn from_rgb(width: u32, height: u32, rgb: Vec<u8>) -> Result<Frame, FrameError> {
        if width == 0 || height == 0 {
            return Err(FrameError::Empty { width, height });
        }
        let expected = width as usize * height as usize * 3;
        if rgb.len() != expected {
            return Err(FrameError::BadBuffer {
                width,
                height,
                len: rgb.len(),
                expected,
            });
        }
        Ok(Frame { width, height, rgb })
    }

    /// A frame of one colour.
    pub fn solid(width: u32, height: u32, rgb: [u8; 3]) -> Frame {
        let n = width as usize * height as usize;
        let mut data = Vec::with_capacity(n * 3);
        for _ in 0..n {
            data.extend_from_slice(&rgb);
        }
        Frame {
            width,
            height,
            rgb: data,
        }
    }

    /// Write the frame as three planes `[3, H, W]` of `f32` in `[0, 1]`
    /// (`value / 255`) into `out`, plane `c` starting at `c * plane_stride`.
    /// This is the one u8 -> f32 conversion used by `Window` and the model.
    pub fn write_chw(&self, out: &mut [f32], plane_stride: usize) {
        let hw = self.width as usize * self.height as usize;
        for (p, px) in self.rgb.chunks_exact(3).enumerate().take(hw) {
            for (c, &v) in px.iter().enumerate() {
                out[c * plane_stride + p] = f32::from(v) / 255.0;
            }
        }
    }
}

/// Decode a compressed image (`format` as in `sensor_msgs/CompressedImage`:
/// contains `jpeg`/`jpg` or `png`; empty means "guess from the bytes") and
/// resize it to `size x size` with [`resize_area`].
pub fn decode_compressed(format: &str, data: &[u8], size: u32) -> Result<Frame, FrameError> {
    decode_as(image_format(format, data)?, data, size)
}

/// The image format `format` names (see [`decode_compressed`]).
fn image_format(format: &str, data: &[u8]) -> Result<ImageFormat, FrameError> {
    let lower = format.to_ascii_lowercase();
    if lower.contains("jpeg") || lower.contains("jpg") {
        Ok(ImageFormat::Jpeg)
    } else if lower.contains("png") {
        Ok(ImageFormat::Png)
    } else if lower.trim().is_empty() {
        match image::guess_format(data) {
            Ok(f @ (ImageFormat::Jpeg | ImageFormat::Png)) => Ok(f),
            _ => Err(FrameError::UnsupportedFormat {
                format: format.to_string(),
            }),
        }
    } else {
        Err(FrameError::UnsupportedFormat {
            format: format.to_string(),
        })
    }
}

/// Decodes `data` as `image_format` (JPEG or PNG) and resizes it.
fn decode_as(image_format: ImageFormat, data: &[u8], size: u32) -> Result<Frame, FrameError> {
    let name = if image_format == ImageFormat::Jpeg {
        "jpeg"
    } else {
        "png"
    };
    let decoded = image::load_from_memory_with_format(data, image_format).map_err(|e| {
        FrameError::Decode {
            format: name,
            len: data.len(),
            reason: e.to_string(),
        }
    })?;
    let rgb = decoded.to_rgb8();
    let (width, height) = rgb.dimensions();
    let frame = Frame::from_rgb(width, height, rgb.into_raw())?;
    resize_area(&frame, size)
}

/// A compressed image kept as recorded (the JPEG or PNG bytes), checked
/// once to decode, and decoded again, to the same bytes
/// ([`decode_compressed`]), each time it is needed. Training and evaluation
/// hold the frames of a split this way: a 64 x 64 JPEG of the simulator is
/// 1.4-1.8 KB, against 12 KB decoded.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CompressedFrame {
    jpeg: bool,
    data: Box<[u8]>,
    size: u32,
}

impl CompressedFrame {
    /// Keeps `data` (`format` as in [`decode_compressed`]) once it has
    /// decoded and resized to `size x size`; the error is the decoder's.
    pub fn new(format: &str, data: Vec<u8>, size: u32) -> Result<CompressedFrame, FrameError> {
        let image_format = image_format(format, &data)?;
        decode_as(image_format, &data, size)?;
        Ok(CompressedFrame {
            jpeg: image_format == ImageFormat::Jpeg,
            data: data.into_boxed_slice(),
            size,
        })
    }

    /// The frame, `size x size`: the bytes [`decode_compressed`] gives.
    pub fn decode(&self) -> Result<Frame, FrameError> {
        let image_format = if self.jpeg {
            ImageFormat::Jpeg
        } else {
            ImageFormat::Png
        };
        decode_as(image_format, &self.data, self.size)
    }

    /// The side it decodes to.
    pub fn size(&self) -> u32 {
        self.size
    }

    /// Bytes held.
    pub fn compressed_len(&self) -> usize {
        self.data.len()
    }
}

/// Encode a frame as JPEG (quality 0-100); used by the recorder and tests.
pub fn encode_jpeg(frame: &Frame, quality: u8) -> Result<Vec<u8>, FrameError> {
    check(frame)?;
    let mut out = Vec::new();
    let mut encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality);
    encoder
        .encode(
            &frame.rgb,
            frame.width,
            frame.height,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| FrameError::Decode {
            format: "jpeg",
            len: frame.rgb.len(),
            reason: format!("encoding failed: {e}"),
        })?;
    Ok(out)
}

/// Encode a frame as PNG (lossless); used by tests.
pub fn encode_png(frame: &Frame) -> Result<Vec<u8>, FrameError> {
    let mut out = std::io::Cursor::new(Vec::new());
    let img = image::RgbImage::from_raw(frame.width, frame.height, frame.rgb.clone()).ok_or(
        FrameError::BadBuffer {
            width: frame.width,
            height: frame.height,
            len: frame.rgb.len(),
            expected: frame.width as usize * frame.height as usize * 3,
        },
    )?;
    img.write_to(&mut out, ImageFormat::Png)
        .map_err(|e| FrameError::Decode {
            format: "png",
            len: frame.rgb.len(),
            reason: format!("encoding failed: {e}"),
        })?;
    Ok(out.into_inner())
}

/// Resize to `size x size` by area averaging: each output pixel is the mean
/// of the source area it covers, each source pixel weighted by the fraction
/// of it inside that area (a box filter, separable: rows then columns, in
/// `f32`, rounded half up to `u8`). The aspect ratio is not kept (a 4:3
/// camera image is squeezed to a square, the same way in training and live).
/// Identity, byte for byte, when the frame is already `size x size`.
pub fn resize_area(frame: &Frame, size: u32) -> Result<Frame, FrameError> {
    if size == 0 {
        return Err(FrameError::Empty {
            width: size,
            height: size,
        });
    }
    check(frame)?;
    if frame.width == size && frame.height == size {
        return Ok(frame.clone());
    }
    let (w, h, s) = (frame.width as usize, frame.height as usize, size as usize);
    let wx = area_weights(w, s);
    let wy = area_weights(h, s);
    // Horizontal pass: [h, s, 3] in f32.
    let mut tmp = vec![0f32; h * s * 3];
    for y in 0..h {
        let row = &frame.rgb[y * w * 3..(y + 1) * w * 3];
        for (ox, taps) in wx.iter().enumerate() {
            for &(ix, weight) in taps {
                for c in 0..3 {
                    tmp[(y * s + ox) * 3 + c] += weight * f32::from(row[ix * 3 + c]);
                }
            }
        }
    }
    // Vertical pass.
    let mut out = vec![0u8; s * s * 3];
    for (oy, taps) in wy.iter().enumerate() {
        for ox in 0..s {
            for c in 0..3 {
                let mut acc = 0f32;
                for &(iy, weight) in taps {
                    acc += weight * tmp[(iy * s + ox) * 3 + c];
                }
                out[(oy * s + ox) * 3 + c] = (acc + 0.5).clamp(0.0, 255.0) as u8;
            }
        }
    }
    Frame::from_rgb(size, size, out)
}

/// Error unless the buffer holds width x height RGB pixels.
fn check(frame: &Frame) -> Result<(), FrameError> {
    let expected = frame.width as usize * frame.height as usize * 3;
    if frame.width == 0 || frame.height == 0 || frame.rgb.len() != expected {
        return Err(FrameError::BadBuffer {
            width: frame.width,
            height: frame.height,
            len: frame.rgb.len(),
            expected,
        });
    }
    Ok(())
}

/// For each of `out_len` output cells, the source indices it covers and
/// their weights (overlap length / cell length; they sum to 1).
fn area_weights(in_len: usize, out_len: usize) -> Vec<Vec<(usize, f32)>> {
    let scale = in_len as f64 / out_len as f64;
    (0..out_len)
        .map(|o| {
            let start = o as f64 * scale;
            let end = (o + 1) as f64 * scale;
            let first = start.floor() as usize;
            let last = (end.ceil() as usize).min(in_len);
            let mut taps = Vec::with_capacity(last - first);
            for i in first..last {
                let overlap = (end.min((i + 1) as f64) - start.max(i as f64)).max(0.0);
                if overlap > 0.0 {
                    taps.push((i, (overlap / scale) as f32));
                }
            }
            taps
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gradient(w: u32, h: u32) -> Frame {
        let mut rgb = Vec::new();
        for y in 0..h {
            for x in 0..w {
                rgb.extend_from_slice(&[
                    (x * 7 % 256) as u8,
                    (y * 5 % 256) as u8,
                    ((x + y) % 256) as u8,
                ]);
            }
        }
        Frame::from_rgb(w, h, rgb).unwrap()
    }

    #[test]
    fn resize_is_identity_at_size() {
        let f = gradient(64, 64);
        assert_eq!(resize_area(&f, 64).unwrap(), f);
    }

    #[test]
    fn resize_halves_by_averaging_2x2_blocks() {
        let f = gradient(8, 8);
        let r = resize_area(&f, 4).unwrap();
        for oy in 0..4usize {
            for ox in 0..4usize {
                for c in 0..3 {
                    let mut sum = 0u32;
                    for dy in 0..2 {
                        for dx in 0..2 {
                            sum += u32::from(f.rgb[((oy * 2 + dy) * 8 + ox * 2 + dx) * 3 + c]);
                        }
                    }
                    let expected = ((sum as f32 / 4.0) + 0.5) as u8;
                    assert_eq!(r.rgb[(oy * 4 + ox) * 3 + c], expected);
                }
            }
        }
    }

    #[test]
    fn resize_keeps_solid_colour_for_any_ratio() {
        let f = Frame::solid(97, 61, [10, 200, 77]);
        let r = resize_area(&f, 64).unwrap();
        assert_eq!(r, Frame::solid(64, 64, [10, 200, 77]));
    }

    #[test]
    fn png_round_trip_is_exact_and_jpeg_close() {
        let f = gradient(64, 64);
        let png = encode_png(&f).unwrap();
        assert_eq!(decode_compressed("png", &png, 64).unwrap(), f);
        assert_eq!(decode_compressed("", &png, 64).unwrap(), f);
        let solid = Frame::solid(64, 64, [200, 40, 90]);
        let jpeg = encode_jpeg(&solid, 95).unwrap();
        let back = decode_compressed("bgr8; jpeg compressed bgr8", &jpeg, 64).unwrap();
        for (a, b) in back.rgb.iter().zip(&solid.rgb) {
            assert!((i32::from(*a) - i32::from(*b)).abs() <= 3);
        }
    }

    #[test]
    fn bad_input_is_an_error() {
        assert!(matches!(
            decode_compressed("jpeg", &[1, 2, 3], 64),
            Err(FrameError::Decode { .. })
        ));
        assert!(matches!(
            decode_compressed("tiff", &[1, 2, 3], 64),
            Err(FrameError::UnsupportedFormat { .. })
        ));
        assert!(matches!(
            Frame::from_rgb(2, 2, vec![0; 11]),
            Err(FrameError::BadBuffer { .. })
        ));
    }

    #[test]
    fn a_compressed_frame_decodes_to_the_bytes_of_decode_compressed() {
        let f = gradient(80, 60);
        let jpeg = encode_jpeg(&f, 90).unwrap();
        let png = encode_png(&f).unwrap();
        for (format, data) in [("jpeg", &jpeg), ("", &png), ("png", &png)] {
            let c = CompressedFrame::new(format, data.clone(), 32).unwrap();
            assert_eq!(c.size(), 32);
            assert_eq!(c.compressed_len(), data.len());
            assert_eq!(
                c.decode().unwrap(),
                decode_compressed(format, data, 32).unwrap()
            );
        }
        assert!(matches!(
            CompressedFrame::new("jpeg", vec![1, 2, 3], 32),
            Err(FrameError::Decode { .. })
        ));
        assert!(matches!(
            CompressedFrame::new("tiff", png.clone(), 32),
            Err(FrameError::UnsupportedFormat { .. })
        ));
    }

    #[test]
    fn chw_planes_in_unit_range() {
        let f = Frame::solid(2, 2, [255, 0, 51]);
        let mut out = vec![-1f32; 12];
        f.write_chw(&mut out, 4);
        assert_eq!(&out[0..4], &[1.0; 4]);
        assert_eq!(&out[4..8], &[0.0; 4]);
        assert_eq!(&out[8..12], &[0.2; 4]);
    }
}
