//! Frame files: PNG, JPEG, TIFF and binary PGM decoded into the core's grey frames, and grey
//! frames written back as PNG or PGM (the renderer's output, the tests' input).
//!
//! 8-bit files stay 8-bit; 16-bit ones stay 16-bit (the detector uses every bit). Colour is
//! converted to luma (Rec. 709 weights, as the `image` crate does; a JPEG's own luma plane is
//! taken as it is); an alpha channel is dropped. JPEG is lossy: its blocks move disc centres by
//! hundredths of a pixel, so it is read, never written, and calibration reports say so.
//!
//! Memory is bounded before any pixel is decoded: the size is read from the header first, so a
//! frame of the wrong size, or a file that claims an enormous one, costs nothing; every decoder
//! may allocate at most [`decode_budget_bytes`] of the frame's size; PNG's ancillary chunks
//! (text, colour profiles), which may be compressed bombs, are skipped unread. PNG goes
//! through the `png` crate directly (the `image` crate decompresses them), JPEG through
//! `zune-jpeg` (its luma plane, without a colour conversion), TIFF and PGM through `image`.

use crate::vision::{BitDepth, GreyImage};
use image::{ColorType, DynamicImage, ImageFormat, ImageReader, Limits};
use std::io::Cursor;
use std::path::Path;

/// The file formats a frame can come in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameFormat {
    /// `image/png`.
    Png,
    /// `image/jpeg` (lossy: read only).
    Jpeg,
    /// `image/tiff`.
    Tiff,
    /// Binary PGM (P5), `image/x-portable-graymap`.
    Pgm,
}

impl FrameFormat {
    /// Every format, for messages.
    pub const ALL: [FrameFormat; 4] = [
        FrameFormat::Png,
        FrameFormat::Jpeg,
        FrameFormat::Tiff,
        FrameFormat::Pgm,
    ];

    /// The media type.
    pub fn content_type(self) -> &'static str {
        match self {
            FrameFormat::Png => "image/png",
            FrameFormat::Jpeg => "image/jpeg",
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

    /// The format a file name's extension names (`.png`, `.jpg`/`.jpeg`, `.tif`/`.tiff`,
    /// `.pgm`).
    pub fn from_path(path: &Path) -> Option<Self> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "png" => Some(FrameFormat::Png),
            "jpg" | "jpeg" => Some(FrameFormat::Jpeg),
            "tif" | "tiff" => Some(FrameFormat::Tiff),
            "pgm" => Some(FrameFormat::Pgm),
            _ => None,
        }
    }

    /// True for a lossy format (its compression moves disc centres).
    pub fn is_lossy(self) -> bool {
        self == FrameFormat::Jpeg
    }

    fn image_format(self) -> ImageFormat {
        match self {
            FrameFormat::Png => ImageFormat::Png,
            FrameFormat::Jpeg => ImageFormat::Jpeg,
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

/// The most a decoder may allocate for a frame of `width_px` x `height_px`: four 16-bit
/// channels of every pixel (RGBA 16, the widest kind read), and a megabyte for tables.
pub fn decode_budget_bytes(width_px: u32, height_px: u32) -> u64 {
    u64::from(width_px) * u64::from(height_px) * 8 + (1 << 20)
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
    let check = |(width_px, height_px): (u32, u32)| match expected {
        Some((w, h)) if (w, h) != (width_px, height_px) => Err(FrameFileError::WrongSize {
            width_px,
            height_px,
            expected_width_px: w,
            expected_height_px: h,
        }),
        _ => Ok(()),
    };
    match format {
        FrameFormat::Png => decode_png(bytes, check).map_err(|e| match e {
            Refusal::Size(e) => e,
            Refusal::Decoder(m) => undecodable(&m),
        }),
        FrameFormat::Jpeg => decode_jpeg(bytes, check).map_err(|e| match e {
            Refusal::Size(e) => e,
            Refusal::Decoder(m) => undecodable(&m),
        }),
        FrameFormat::Tiff | FrameFormat::Pgm => {
            let reader = || ImageReader::with_format(Cursor::new(bytes), format.image_format());
            let (width_px, height_px) = reader().into_dimensions().map_err(|e| undecodable(&e))?;
            check((width_px, height_px))?;
            let mut limits = Limits::default();
            limits.max_image_width = Some(width_px);
            limits.max_image_height = Some(height_px);
            limits.max_alloc = Some(decode_budget_bytes(width_px, height_px));
            let mut reader = reader();
            reader.limits(limits);
            let image = reader.decode().map_err(|e| undecodable(&e))?;
            grey_of(image).map_err(|e| undecodable(&e))
        }
    }
}

/// Why a decoder refused a frame: its size, or the data.
enum Refusal {
    Size(FrameFileError),
    Decoder(String),
}

impl<E: std::fmt::Display> From<E> for Refusal {
    fn from(e: E) -> Self {
        Refusal::Decoder(e.to_string())
    }
}

/// Rec. 709 luma in the `image` crate's integer weights (so that a colour frame reads the same
/// whichever way it came).
fn luma(r: u32, g: u32, b: u32) -> u32 {
    (2126 * r + 7152 * g + 722 * b) / 10_000
}

/// PNG through the `png` crate: text and colour-profile chunks skipped unread, allocation
/// bounded by the frame's size.
fn decode_png(
    bytes: &[u8],
    check: impl Fn((u32, u32)) -> Result<(), FrameFileError>,
) -> Result<GreyImage, Refusal> {
    let header = png::Decoder::new(Cursor::new(bytes))
        .read_header_info()?
        .size();
    check(header).map_err(Refusal::Size)?;
    let (w, h) = header;
    let limits = png::Limits {
        bytes: usize::try_from(decode_budget_bytes(w, h)).unwrap_or(usize::MAX),
    };
    let mut decoder = png::Decoder::new_with_limits(Cursor::new(bytes), limits);
    decoder.set_ignore_text_chunk(true);
    decoder.set_ignore_iccp_chunk(true);
    // Palettes and bit depths under 8 expanded to 8 bit; 16 bit kept.
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info()?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| Refusal::Decoder("the frame is too large to hold".to_owned()))?;
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf)?;
    buf.truncate(info.buffer_size());
    let channels = info.color_type.samples();
    let n = (w as usize) * (h as usize);
    let grey = match info.bit_depth {
        png::BitDepth::Sixteen => {
            let px = |i: usize, c: usize| {
                let at = 2 * (i * channels + c);
                u32::from(u16::from_be_bytes([buf[at], buf[at + 1]]))
            };
            let pixels: Vec<u16> = (0..n)
                .map(|i| match channels {
                    1 | 2 => px(i, 0) as u16,
                    _ => luma(px(i, 0), px(i, 1), px(i, 2)) as u16,
                })
                .collect();
            GreyImage::new(w, h, BitDepth::Sixteen, pixels)?
        }
        _ => {
            let pixels: Vec<u8> = match channels {
                1 => buf,
                2 => buf.iter().step_by(2).copied().collect(),
                _ => buf
                    .chunks_exact(channels)
                    .map(|p| luma(p[0].into(), p[1].into(), p[2].into()) as u8)
                    .collect(),
            };
            GreyImage::from_u8(w, h, &pixels)?
        }
    };
    Ok(grey)
}

/// JPEG through `zune-jpeg`: its luma plane (the Y of YCbCr, as the camera encoded it), the
/// size checked from the header first.
fn decode_jpeg(
    bytes: &[u8],
    check: impl Fn((u32, u32)) -> Result<(), FrameFileError>,
) -> Result<GreyImage, Refusal> {
    use zune_jpeg::zune_core::bytestream::ZCursor;
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    let mut probe = zune_jpeg::JpegDecoder::new(ZCursor::new(bytes));
    probe.decode_headers()?;
    // The decoder fills what a cut file lacks with grey: a file whose last scan has no end
    // marker after it is refused, as a cut PNG is (no marker can occur inside a scan's data,
    // where every 0xFF byte is followed by 0x00 or a restart marker).
    let last = |marker: u8| bytes.windows(2).rposition(|w| w == [0xFF, marker]);
    if last(0xD9).is_none_or(|eoi| last(0xDA).is_some_and(|sos| eoi < sos)) {
        return Err(Refusal::Decoder(
            "the data ends before the image's end marker: the file was cut".to_owned(),
        ));
    }
    let (w, h) = probe
        .info()
        .map(|i| (u32::from(i.width), u32::from(i.height)))
        .ok_or_else(|| Refusal::Decoder("no frame header".to_owned()))?;
    check((w, h)).map_err(Refusal::Size)?;
    let options = DecoderOptions::default()
        .jpeg_set_out_colorspace(ColorSpace::Luma)
        .set_max_width(w as usize)
        .set_max_height(h as usize);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), options);
    let pixels = decoder.decode()?;
    Ok(GreyImage::from_u8(w, h, &pixels)?)
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

/// A grey 8-bit frame as JPEG of `quality` (1 to 100): lossy, for frames as compressing
/// cameras and camera computers send them, and for the tests and the demo that stand in for
/// them.
pub fn encode_jpeg(image: &GreyImage, quality: u8) -> Result<Vec<u8>, FrameFileError> {
    use image::codecs::jpeg::JpegEncoder;
    let dynamic = to_dynamic(image, FrameFormat::Png)?.into_luma8();
    let mut out = Vec::new();
    JpegEncoder::new_with_quality(&mut out, quality.clamp(1, 100))
        .encode_image(&dynamic)
        .map_err(|e| FrameFileError::Undecodable {
            format: FrameFormat::Jpeg,
            reason: e.to_string(),
        })?;
    Ok(out)
}

/// An 8-bit RGB frame (`rgb` row by row, three bytes a pixel) as a colour PNG, or a colour JPEG
/// of `quality`.
pub fn encode_rgb(
    width_px: u32,
    height_px: u32,
    rgb: Vec<u8>,
    format: FrameFormat,
    quality: u8,
) -> Result<Vec<u8>, FrameFileError> {
    let failed = |reason: String| FrameFileError::Undecodable { format, reason };
    let buffer = image::RgbImage::from_raw(width_px, height_px, rgb)
        .ok_or_else(|| failed("the pixels do not fill the size".to_owned()))?;
    let mut out = Cursor::new(Vec::new());
    match format {
        FrameFormat::Jpeg => {
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality.clamp(1, 100))
                .encode_image(&buffer)
                .map_err(|e| failed(e.to_string()))?
        }
        _ => DynamicImage::ImageRgb8(buffer)
            .write_to(&mut out, format.image_format())
            .map_err(|e| failed(e.to_string()))?,
    }
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
