//! The head camera opened directly through V4L2 (nokhwa, cargo feature
//! `camera-v4l`), and the decoding of its raw frames into the model's input.
//!
//! Frames enter as the camera's raw buffers (MJPEG or YUYV at the
//! configured size, `[camera]` in the config); [`decode_raw`] turns each one
//! into an S x S RGB [`Frame`] once, on arrival, with the data plane's
//! decoder and area resize (`frame.rs`: the whole picture squeezed to a
//! square, exactly as recorded frames are), so live frames match training. They leave through the camera's
//! [`StreamFeed`]. Decoding does not need a camera and is tested on its own.
//! The capture loop is a blocking thread; a camera that fails to open or
//! stops delivering is counted, logged once per kind, and reopened with
//! backoff until shutdown.

pub use crate::config::sources::{CameraConfig, PixelFormat};
use crate::frame::{decode_compressed, encode_jpeg, resize_area, Frame};
use crate::msgs::{CompressedImage, Header, Time};

use thiserror::Error;

#[derive(Debug, Error, PartialEq)]
pub enum CameraError {
    #[error("{format:?} frame {width}x{height}: expected {expected} bytes, got {got}")]
    BufferSize {
        format: PixelFormat,
        width: u32,
        height: u32,
        expected: usize,
        got: usize,
    },
    #[error("MJPEG frame: cannot decode the JPEG: {0}")]
    Jpeg(String),
    #[error("frame: {0}")]
    Frame(String),
    #[error("frame of {width}x{height} pixels is empty or odd-sized for {format:?}")]
    Size {
        format: PixelFormat,
        width: u32,
        height: u32,
    },
}

/// One raw camera buffer -> the model's S x S RGB frame.
pub fn decode_raw(
    format: PixelFormat,
    width: u32,
    height: u32,
    data: &[u8],
    size: u32,
) -> Result<Frame, CameraError> {
    match format {
        // The same decoder and resize as `/head_camera/image_raw/compressed`
        // and the recordings.
        PixelFormat::Mjpeg => {
            decode_compressed("jpeg", data, size).map_err(|e| CameraError::Jpeg(e.to_string()))
        }
        PixelFormat::Yuyv => {
            let rgb = yuyv_to_rgb(width, height, data)?;
            let frame = Frame::from_rgb(width, height, rgb)
                .map_err(|e| CameraError::Frame(e.to_string()))?;
            resize_area(&frame, size).map_err(|e| CameraError::Frame(e.to_string()))
        }
    }
}

/// JPEG quality of a raw (YUYV) frame kept by `record`.
pub const RECORD_JPEG_QUALITY: u8 = 90;

/// One raw camera buffer as `record` keeps it, at the camera's own size: an
/// MJPEG buffer unchanged, a YUYV one encoded once as JPEG; `format`
/// `"jpeg"`, `header.stamp` the capture time, `frame_id` `"head_camera"`.
pub fn compressed_raw(
    format: PixelFormat,
    width: u32,
    height: u32,
    data: &[u8],
    stamp_ns: i64,
) -> Result<CompressedImage, CameraError> {
    let data = match format {
        PixelFormat::Mjpeg => data.to_vec(),
        PixelFormat::Yuyv => {
            let rgb = yuyv_to_rgb(width, height, data)?;
            let frame = Frame::from_rgb(width, height, rgb)
                .map_err(|e| CameraError::Frame(e.to_string()))?;
            encode_jpeg(&frame, RECORD_JPEG_QUALITY)
                .map_err(|e| CameraError::Frame(e.to_string()))?
        }
    };
    Ok(CompressedImage {
        header: Header {
            stamp: Time::from_ns(stamp_ns),
            frame_id: "head_camera".into(),
        },
        format: "jpeg".into(),
        data,
    })
}

/// YUYV 4:2:2 (Y0 U Y1 V per two pixels, BT.601 limited range) -> RGB8.
pub fn yuyv_to_rgb(width: u32, height: u32, data: &[u8]) -> Result<Vec<u8>, CameraError> {
    if width == 0 || height == 0 || !width.is_multiple_of(2) {
        return Err(CameraError::Size {
            format: PixelFormat::Yuyv,
            width,
            height,
        });
    }
    let pixels = width as usize * height as usize;
    let expected = pixels * 2;
    if data.len() != expected {
        return Err(CameraError::BufferSize {
            format: PixelFormat::Yuyv,
            width,
            height,
            expected,
            got: data.len(),
        });
    }
    let mut rgb = Vec::with_capacity(pixels * 3);
    for quad in data.chunks_exact(4) {
        let (u, v) = (f32::from(quad[1]) - 128.0, f32::from(quad[3]) - 128.0);
        for y in [quad[0], quad[2]] {
            let c = 1.164 * (f32::from(y) - 16.0);
            let to_u8 = |x: f32| x.round().clamp(0.0, 255.0) as u8;
            rgb.push(to_u8(c + 1.596 * v));
            rgb.push(to_u8(c - 0.392 * u - 0.813 * v));
            rgb.push(to_u8(c + 2.017 * u));
        }
    }
    Ok(rgb)
}

#[cfg(feature = "camera-v4l")]
pub use capture::{spawn_camera, spawn_camera_compressed};

#[cfg(feature = "camera-v4l")]
mod capture {
    //! The blocking capture thread (nokhwa V4L2).
    use std::sync::Arc;
    use std::thread::JoinHandle;
    use std::time::Duration;

    use nokhwa::pixel_format::RgbFormat;
    use nokhwa::utils::{
        CameraFormat, CameraIndex, FrameFormat, RequestedFormat, RequestedFormatType, Resolution,
    };
    use nokhwa::Camera;

    use super::{compressed_raw, decode_raw, CameraError};
    use super::{CameraConfig, PixelFormat};
    use crate::msgs::CompressedImage;
    use crate::shutdown::Shutdown;
    use crate::streams::sample::Sample;
    use crate::streams::StreamFeed;

    /// The V4L2 index of `/dev/videoN` (nokhwa addresses cameras by index).
    fn index_of(device: &std::path::Path) -> CameraIndex {
        let name = device.to_string_lossy();
        match name
            .strip_prefix("/dev/video")
            .and_then(|n| n.parse::<u32>().ok())
        {
            Some(i) => CameraIndex::Index(i),
            None => CameraIndex::String(name.into_owned()),
        }
    }

    fn open(config: &CameraConfig) -> Result<Camera, nokhwa::NokhwaError> {
        let fourcc = match config.format {
            PixelFormat::Mjpeg => FrameFormat::MJPEG,
            PixelFormat::Yuyv => FrameFormat::YUYV,
        };
        let format = CameraFormat::new(
            Resolution::new(config.width, config.height),
            fourcc,
            config.fps,
        );
        let requested = RequestedFormat::new::<RgbFormat>(RequestedFormatType::Exact(format));
        let mut camera = Camera::new(index_of(&config.device), requested)?;
        camera.open_stream()?;
        Ok(camera)
    }

    /// Start the capture thread: frames go to `feed`, decoded to `size`.
    pub fn spawn_camera(
        config: CameraConfig,
        size: u32,
        feed: StreamFeed<Sample>,
        shutdown: Shutdown,
    ) -> std::io::Result<JoinHandle<()>> {
        let format = config.format;
        spawn_capture(config, feed, shutdown, move |w, h, data, stamp_ns| {
            decode_raw(format, w, h, data, size).map(|frame| Sample::Frame {
                stamp_ns,
                frame: Arc::new(frame),
            })
        })
    }

    /// Start the capture thread for `record`: each buffer goes to `feed` as
    /// the camera gave it ([`compressed_raw`]: MJPEG unchanged, YUYV as one
    /// JPEG at full size).
    pub fn spawn_camera_compressed(
        config: CameraConfig,
        feed: StreamFeed<Arc<CompressedImage>>,
        shutdown: Shutdown,
    ) -> std::io::Result<JoinHandle<()>> {
        let format = config.format;
        spawn_capture(config, feed, shutdown, move |w, h, data, stamp_ns| {
            compressed_raw(format, w, h, data, stamp_ns).map(Arc::new)
        })
    }

    /// The capture loop; `convert(width, height, buffer, stamp_ns)` makes
    /// the stream's value of each buffer.
    fn spawn_capture<T: crate::streams::input::StreamValue>(
        config: CameraConfig,
        feed: StreamFeed<T>,
        shutdown: Shutdown,
        convert: impl Fn(u32, u32, &[u8], i64) -> Result<T, CameraError> + Send + 'static,
    ) -> std::io::Result<JoinHandle<()>> {
        std::thread::Builder::new()
            .name("camera".into())
            .spawn(move || {
                let device = config.device.display().to_string();
                let mut backoff = Duration::from_millis(100);
                while !shutdown.is_shutdown() {
                    let mut camera = match open(&config) {
                        Ok(c) => {
                            tracing::info!(%device, "camera open");
                            feed.stats().set_state(format!("open {device}"));
                            backoff = Duration::from_millis(100);
                            c
                        }
                        Err(e) => {
                            feed.error("open", &format_args!("{device}: {e}"));
                            feed.stats().set_state(format!("reopening {device}"));
                            std::thread::sleep(backoff);
                            backoff = (backoff * 2).min(Duration::from_secs(5));
                            continue;
                        }
                    };
                    while !shutdown.is_shutdown() {
                        let buffer = match camera.frame() {
                            Ok(b) => b,
                            Err(e) => {
                                feed.error("capture", &format_args!("{device}: {e}"));
                                break;
                            }
                        };
                        let stamp_ns = crate::clock::unix_now_ns();
                        let res = buffer.resolution();
                        let value = convert(res.width(), res.height(), buffer.buffer(), stamp_ns)
                            .map_err(|e| crate::streams::input::Rejection::from_frame(&e));
                        let _ = feed.offer(stamp_ns, value);
                    }
                    let _ = camera.stop_stream();
                }
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Encode an RGB image as YUYV (BT.601 limited range), averaging chroma per pair.
    fn rgb_to_yuyv(width: u32, height: u32, rgb: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        for px in rgb.chunks_exact(6).take((width * height / 2) as usize) {
            let yuv = |r: f32, g: f32, b: f32| {
                (
                    16.0 + 0.257 * r + 0.504 * g + 0.098 * b,
                    128.0 - 0.148 * r - 0.291 * g + 0.439 * b,
                    128.0 + 0.439 * r - 0.368 * g - 0.071 * b,
                )
            };
            let f = |i: usize| f32::from(px[i]);
            let (y0, u0, v0) = yuv(f(0), f(1), f(2));
            let (y1, u1, v1) = yuv(f(3), f(4), f(5));
            out.extend([y0, (u0 + u1) / 2.0, y1, (v0 + v1) / 2.0].map(|x| x.round() as u8));
        }
        out
    }

    /// A 640x480 test card: left half red, right half blue, a green band at the top.
    fn test_card() -> (u32, u32, Vec<u8>) {
        let (w, h) = (640u32, 480u32);
        let mut rgb = Vec::with_capacity((w * h * 3) as usize);
        for y in 0..h {
            for x in 0..w {
                let px = if y < 120 {
                    [20, 200, 30]
                } else if x < w / 2 {
                    [210, 30, 20]
                } else {
                    [25, 40, 220]
                };
                rgb.extend(px);
            }
        }
        (w, h, rgb)
    }

    fn pixel(frame: &Frame, x: u32, y: u32) -> [u8; 3] {
        let i = ((y * frame.width + x) * 3) as usize;
        [frame.rgb[i], frame.rgb[i + 1], frame.rgb[i + 2]]
    }

    fn close(a: [u8; 3], b: [u8; 3], tol: i32) -> bool {
        a.iter()
            .zip(b)
            .all(|(&x, y)| (i32::from(x) - i32::from(y)).abs() <= tol)
    }

    #[test]
    fn yuyv_round_trips_within_rounding() {
        let (w, h, rgb) = test_card();
        let back = yuyv_to_rgb(w, h, &rgb_to_yuyv(w, h, &rgb)).expect("decodes");
        assert_eq!(back.len(), rgb.len());
        let worst = rgb
            .iter()
            .zip(&back)
            .map(|(&a, &b)| (i32::from(a) - i32::from(b)).abs())
            .max()
            .unwrap_or(0);
        assert!(worst <= 3, "worst channel error {worst}");
    }

    #[test]
    fn yuyv_frame_becomes_a_square_model_frame() {
        let (w, h, rgb) = test_card();
        let frame =
            decode_raw(PixelFormat::Yuyv, w, h, &rgb_to_yuyv(w, h, &rgb), 64).expect("decodes");
        assert_eq!(
            (frame.width, frame.height, frame.rgb.len()),
            (64, 64, 64 * 64 * 3)
        );
        // The whole picture is squeezed to a square: the red/blue edge stays in the middle.
        assert!(
            close(pixel(&frame, 10, 50), [210, 30, 20], 4),
            "{:?}",
            pixel(&frame, 10, 50)
        );
        assert!(
            close(pixel(&frame, 54, 50), [25, 40, 220], 4),
            "{:?}",
            pixel(&frame, 54, 50)
        );
        // Green band: rows 0..120 of 480 -> rows 0..16 of 64.
        assert!(
            close(pixel(&frame, 32, 5), [20, 200, 30], 4),
            "{:?}",
            pixel(&frame, 32, 5)
        );
    }

    #[test]
    fn mjpeg_frame_becomes_a_square_model_frame() {
        let (w, h, rgb) = test_card();
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 95)
            .encode(&rgb, w, h, image::ExtendedColorType::Rgb8)
            .expect("encode");
        let frame = decode_raw(PixelFormat::Mjpeg, w, h, &jpeg, 64).expect("decodes");
        assert_eq!((frame.width, frame.height), (64, 64));
        assert!(
            close(pixel(&frame, 10, 50), [210, 30, 20], 8),
            "{:?}",
            pixel(&frame, 10, 50)
        );
        assert!(
            close(pixel(&frame, 54, 50), [25, 40, 220], 8),
            "{:?}",
            pixel(&frame, 54, 50)
        );
    }

    #[test]
    fn record_keeps_mjpeg_unchanged_and_yuyv_as_one_full_size_jpeg() {
        let (w, h, rgb) = test_card();
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 95)
            .encode(&rgb, w, h, image::ExtendedColorType::Rgb8)
            .expect("encode");
        let msg = compressed_raw(PixelFormat::Mjpeg, w, h, &jpeg, 1_500_000_000).expect("mjpeg");
        assert_eq!(msg.data, jpeg, "the camera's own bytes");
        assert_eq!(
            (msg.format.as_str(), msg.header.stamp.to_ns()),
            ("jpeg", 1_500_000_000)
        );

        let msg =
            compressed_raw(PixelFormat::Yuyv, w, h, &rgb_to_yuyv(w, h, &rgb), 7).expect("yuyv");
        let full = decode_compressed("jpeg", &msg.data, w).expect("a JPEG");
        let back = image::load_from_memory(&msg.data).expect("decodes");
        assert_eq!((back.width(), back.height()), (w, h), "full size");
        assert_eq!(full.width, w);
        assert!(matches!(
            compressed_raw(PixelFormat::Yuyv, 3, 2, &[0; 12], 0),
            Err(CameraError::Size { .. })
        ));
    }

    #[test]
    fn truncated_or_corrupt_buffers_are_errors_not_panics() {
        let (w, h, rgb) = test_card();
        let yuyv = rgb_to_yuyv(w, h, &rgb);
        assert!(matches!(
            decode_raw(PixelFormat::Yuyv, w, h, &yuyv[..yuyv.len() - 7], 64),
            Err(CameraError::BufferSize { .. })
        ));
        assert!(matches!(
            decode_raw(PixelFormat::Yuyv, 3, 2, &[0; 12], 64),
            Err(CameraError::Size { .. })
        ));
        assert!(matches!(
            decode_raw(
                PixelFormat::Mjpeg,
                w,
                h,
                &[0xFF, 0xD8, 0xFF, 0x00, 1, 2, 3],
                64
            ),
            Err(CameraError::Jpeg(_))
        ));
    }
}
