//! Frame files: PNG, TIFF and binary PGM decoded into the core's grey frames, and grey frames
//! written back as PNG or PGM (the renderer's output, the tests' input).
//!
//! 8-bit files stay 8-bit; 16-bit ones stay 16-bit (the detector uses every bit). Colour is
//! converted to luma (Rec. 709 weights, as the `image` crate does); an alpha channel is dropped.
//! The size is read from the header before any pixel is decoded, so a frame of the wrong size,
//! or a file that claims an enormous one, costs nothing.

use crate::vision::{BitDepth, GreyImage};
use image::{ColorType, DynamicImage, ImageFormat, ImageReader, Limits};
use std::io::Cursor;
use std::path::Path;

/// The file formats a frame can come in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameFormat {
    /// `image/png`.
    Png,
    /// `image/tiff`.
    Tiff,
    /// Binary PGM (P5), `image/x-portable-graymap`.
    Pgm,
}

impl FrameFormat {
    /// Every format, for messages.
    pub const ALL: [FrameFormat; 3] = [FrameFormat::Png, FrameFormat::Tiff, FrameFormat::Pgm];

    /// The media type.
    pub fn content_type(self) -> &'static str {
        match self {
            FrameFormat::Png => "image/png",
            FrameFormat::Tiff => "image/tiff",
            FrameFormat::Pgm => "image/x-portable-graymap",
        }
    }

    /// The format of a `Content-Type` value (parameters ignored).
    pub fn from_content_type(value: &str) -> Option<Self> {
        let essence = value.split(';').next().unwrap_or("").trim();
        Self::ALL
            .into_iter()
            .find(|f| f.content_type().eq_ignore_ascii_case(essence))
    }

    /// The format a file name's extension names (`.png`, `.tif`/`.tiff`, `.pgm`).
    pub fn from_path(path: &Path) -> Option<Self> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "png" => Some(FrameFormat::Png),
            "tif" | "tiff" => Some(FrameFormat::Tiff),
            "pgm" => Some(FrameFormat::Pgm),
            _ => None,
        }
    }

    fn image_format(self) -> ImageFormat {
        match self {
            FrameFormat::Png => ImageFormat::Png,
            FrameFormat::Tiff => ImageFormat::Tiff,
            FrameFormat::Pgm => ImageFormat::Pnm,
        }
    }
}

/// Why a frame file was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FrameFileError {
    /// The bytes are not a frame of the format.
    #[error("the data is not a readable {format:?} image: {reason}")]
    Undecodable {
        /// The format tried.
        format: FrameFormat,
        /// The decoder's words.
        reason: String,
    },
    /// The frame is not the size expected.
    #[error(
        "the frame is {width_px} x {height_px} px but {expected_width_px} x {expected_height_px} px was expected"
    )]
    WrongSize {
        /// Width of the file (px).
        width_px: u32,
        /// Height of the file (px).
        height_px: u32,
        /// Expected width (px).
        expected_width_px: u32,
        /// Expected height (px).
        expected_height_px: u32,
    },
}

/// Decodes a frame; with `expected` (width, height) a frame of another size is refused before
/// its pixels are decoded.
pub fn decode(
    bytes: &[u8],
    format: FrameFormat,
    expected: Option<(u32, u32)>,
) -> Result<GreyImage, FrameFileError> {
    let undecodable = |e: &dyn std::fmt::Display| FrameFileError::Undecodable {
        format,
        reason: e.to_string(),
    };
    let reader = || ImageReader::with_format(Cursor::new(bytes), format.image_format());
    let (width_px, height_px) = reader().into_dimensions().map_err(|e| undecodable(&e))?;
    if let Some((w, h)) = expected
        && (w, h) != (width_px, height_px)
    {
        return Err(FrameFileError::WrongSize {
            width_px,
            height_px,
            expected_width_px: w,
            expected_height_px: h,
        });
    }
    let mut limits = Limits::default();
    limits.max_image_width = Some(width_px);
    limits.max_image_height = Some(height_px);
    let mut reader = reader();
    reader.limits(limits);
    let image = reader.decode().map_err(|e| undecodable(&e))?;
    grey_of(image).map_err(|e| undecodable(&e))
}

/// The grey frame of a decoded image: 8-bit kinds as 8 bit, the rest as 16 bit (a grey image
/// is taken as it is, without a conversion's copy).
fn grey_of(image: DynamicImage) -> Result<GreyImage, crate::vision::VisionError> {
    let (w, h) = (image.width(), image.height());
    match image.color() {
        ColorType::L8 | ColorType::La8 | ColorType::Rgb8 | ColorType::Rgba8 => {
            GreyImage::from_u8(w, h, image.into_luma8().as_raw())
        }
        _ => GreyImage::new(w, h, BitDepth::Sixteen, image.into_luma16().into_raw()),
    }
}

/// Encodes a grey frame losslessly.
pub fn encode(image: &GreyImage, format: FrameFormat) -> Result<Vec<u8>, FrameFileError> {
    let dynamic = to_dynamic(image, format)?;
    let mut out = Cursor::new(Vec::new());
    dynamic
        .write_to(&mut out, format.image_format())
        .map_err(|e| FrameFileError::Undecodable {
            format,
            reason: e.to_string(),
        })?;
    Ok(out.into_inner())
}

/// A grey frame as PNG written for speed rather than size (fast deflate): lossless like
/// [`encode`], several times quicker to write and somewhat larger, for frames written as they
/// arrive (the archive, the latest frame a page asks for).
pub fn encode_png_fast(image: &GreyImage) -> Result<Vec<u8>, FrameFileError> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    let dynamic = to_dynamic(image, FrameFormat::Png)?;
    let mut out = Vec::new();
    dynamic
        .write_with_encoder(PngEncoder::new_with_quality(
            &mut out,
            CompressionType::Fast,
            FilterType::Adaptive,
        ))
        .map_err(|e| FrameFileError::Undecodable {
            format: FrameFormat::Png,
            reason: e.to_string(),
        })?;
    Ok(out)
}

fn to_dynamic(image: &GreyImage, format: FrameFormat) -> Result<DynamicImage, FrameFileError> {
    let (w, h) = (image.width_px(), image.height_px());
    let dynamic = match image.depth() {
        BitDepth::Eight => {
            let bytes: Vec<u8> = image
                .pixels()
                .iter()
                .map(|&v| u8::try_from(v).unwrap_or(u8::MAX))
                .collect();
            image::GrayImage::from_raw(w, h, bytes).map(DynamicImage::ImageLuma8)
        }
        BitDepth::Sixteen => image::ImageBuffer::from_raw(w, h, image.pixels().to_vec())
            .map(DynamicImage::ImageLuma16),
    };
    dynamic.ok_or_else(|| FrameFileError::Undecodable {
        format,
        reason: "the frame's pixel count does not match its size".to_owned(),
    })
}
