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
//! `zune-jpeg` (its luma plane, without a colour conversion), TIFF through `image`. Binary PGM
//! of 8 or 16 full bits (maximum value 255 or 65535), a camera's raw frame, is read here: a
//! header of four numbers and the pixels as they are, widened straight from the request's
//! bytes into the frame (the `image` crate's reader copies them twice on the way, a fifth of
//! the decoding of a 1600 x 1200 frame); other maximum values, which `image` rescales, go
//! through it.

use crate::vision::{BitDepth, GreyImage, StoredPixels};
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
        FrameFormat::Pgm if let Some(header) = PgmHeader::read(bytes) => {
            check((header.width_px, header.height_px))?;
            header.decode(bytes).map_err(|m| undecodable(&m))
        }
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

/// The header of a binary PGM (P5) of 8 or 16 full bits: its size, depth and where its pixels
/// start. `None` for anything else (another maximum value, a malformed header), which the
/// `image` crate's reader then reads or refuses in its own words.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct PgmHeader {
    width_px: u32,
    height_px: u32,
    depth: BitDepth,
    /// The offset of the first pixel byte.
    data_at: usize,
}

impl PgmHeader {
    /// Netpbm's header: `P5`, then width, height and maximum value as decimal numbers, each
    /// after whitespace and any `#` comments (to the end of their line), then one whitespace
    /// byte before the pixels.
    fn read(bytes: &[u8]) -> Option<Self> {
        let mut at = 2;
        if bytes.get(..2)? != b"P5" {
            return None;
        }
        let mut number = || -> Option<u32> {
            loop {
                match *bytes.get(at)? {
                    b' ' | b'\t' | b'\n' | b'\r' | 0x0b | 0x0c => at += 1,
                    b'#' => {
                        while !matches!(*bytes.get(at)?, b'\n' | b'\r') {
                            at += 1;
                        }
                    }
                    _ => break,
                }
            }
            let start = at;
            let mut value = 0u32;
            while let Some(&d) = bytes.get(at).filter(|d| d.is_ascii_digit()) {
                value = value.checked_mul(10)?.checked_add(u32::from(d - b'0'))?;
                at += 1;
            }
            (at > start).then_some(value)
        };
        let (width_px, height_px, max) = (number()?, number()?, number()?);
        let depth = match max {
            255 => BitDepth::Eight,
            65535 => BitDepth::Sixteen,
            _ => return None,
        };
        if width_px == 0
            || height_px == 0
            || !matches!(bytes.get(at)?, b' ' | b'\t' | b'\n' | b'\r' | 0x0b | 0x0c)
        {
            return None;
        }
        Some(PgmHeader {
            width_px,
            height_px,
            depth,
            data_at: at + 1,
        })
    }

    /// The frame: 8-bit pixels as they are, 16-bit ones most significant byte first. Bytes
    /// after the frame (a second image of a multi-image file) are not read.
    fn decode(self, bytes: &[u8]) -> Result<GreyImage, String> {
        let n = self.width_px as usize * self.height_px as usize;
        let per = match self.depth {
            BitDepth::Eight => 1,
            BitDepth::Sixteen => 2,
        };
        let data = &bytes[self.data_at..];
        let Some(data) = data.get(..n * per) else {
            return Err(format!(
                "the data ends after {} of the {} bytes of a {} x {} frame's pixels: the file was cut",
                data.len(),
                n * per,
                self.width_px,
                self.height_px
            ));
        };
        let image = match self.depth {
            BitDepth::Eight => GreyImage::from_u8(self.width_px, self.height_px, data),
            BitDepth::Sixteen => GreyImage::new(
                self.width_px,
                self.height_px,
                BitDepth::Sixteen,
                data.chunks_exact(2)
                    .map(|b| u16::from_be_bytes([b[0], b[1]]))
                    .collect(),
            ),
        };
        image.map_err(|e| e.to_string())
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
            GreyImage::from_u8_vec(w, h, pixels)?
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
    Ok(GreyImage::from_u8_vec(w, h, pixels)?)
}

/// The grey frame of a decoded image: 8-bit kinds as 8 bit, the rest as 16 bit (a grey image
/// is taken as it is, without a conversion's copy).
fn grey_of(image: DynamicImage) -> Result<GreyImage, crate::vision::VisionError> {
    let (w, h) = (image.width(), image.height());
    match image.color() {
        ColorType::L8 | ColorType::La8 | ColorType::Rgb8 | ColorType::Rgba8 => {
            GreyImage::from_u8_vec(w, h, image.into_luma8().into_raw())
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
    let dynamic = match image.stored() {
        StoredPixels::Eight(bytes) => {
            image::GrayImage::from_raw(w, h, bytes.to_vec()).map(DynamicImage::ImageLuma8)
        }
        StoredPixels::Sixteen(pixels) => {
            image::ImageBuffer::from_raw(w, h, pixels.to_vec()).map(DynamicImage::ImageLuma16)
        }
    };
    dynamic.ok_or_else(|| FrameFileError::Undecodable {
        format,
        reason: "the frame's pixel count does not match its size".to_owned(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The `image` crate's reading of a PGM, the reference for the header read here.
    fn through_image(bytes: &[u8]) -> GreyImage {
        let image = ImageReader::with_format(Cursor::new(bytes), ImageFormat::Pnm)
            .decode()
            .expect("image reads it");
        grey_of(image).expect("grey")
    }

    /// A P5 file of these pixels, with a comment and the given whitespace between its fields.
    fn pgm(w: u32, h: u32, sixteen: bool, pixels: &[u16], gaps: [&str; 4]) -> Vec<u8> {
        let max = if sixteen { 65535 } else { 255 };
        let mut file =
            format!("P5{}{w}{}{h}{}{max}{}", gaps[0], gaps[1], gaps[2], gaps[3]).into_bytes();
        for &p in pixels {
            if sixteen {
                file.extend(p.to_be_bytes());
            } else {
                file.push(p as u8);
            }
        }
        file
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Any 8- or 16-bit P5 file, with comments and any whitespace in its header, reads as
        /// the `image` crate reads it: the same size, depth and pixels.
        #[test]
        fn binary_pgm_reads_as_the_image_crate_reads_it(
            (w, h, words) in (1u32..40, 1u32..30).prop_flat_map(|(w, h)| {
                (Just(w), Just(h), prop::collection::vec(any::<u16>(), (w * h) as usize))
            }),
            sixteen in any::<bool>(),
            gaps in prop::array::uniform4(prop::sample::select(vec![
                " ", "\n", "\t", "\r\n", "  \n# a comment, 12 34\n", "\n#\n",
            ])),
        ) {
            let pixels: Vec<u16> = if sixteen {
                words
            } else {
                words.iter().map(|&v| v & 0xff).collect()
            };
            // The byte after the maximum value is the only one before the pixels.
            let last = if gaps[3].ends_with('\n') { "\n" } else { " " };
            let file = pgm(w, h, sixteen, &pixels, [gaps[0], gaps[1], gaps[2], last]);
            let header = PgmHeader::read(&file).expect("read here");
            prop_assert_eq!((header.width_px, header.height_px), (w, h));
            let ours = decode(&file, FrameFormat::Pgm, Some((w, h))).expect("decodes");
            let theirs = through_image(&file);
            prop_assert_eq!(ours.depth(), theirs.depth());
            prop_assert_eq!(ours.pixels(), theirs.pixels());
            prop_assert_eq!(&ours.pixels()[..], &pixels[..]);
        }
    }

    #[test]
    fn a_cut_or_wrong_sized_pgm_is_refused_by_name_and_other_depths_go_through_image() {
        let pixels: Vec<u16> = (0..12).map(|i| i * 20).collect();
        let file = pgm(4, 3, false, &pixels, [" ", " ", " ", "\n"]);
        let cut = decode(&file[..file.len() - 1], FrameFormat::Pgm, None).unwrap_err();
        assert!(
            matches!(&cut, FrameFileError::Undecodable { reason, .. } if reason.contains("11 of the 12 bytes") && reason.contains("cut")),
            "{cut}"
        );
        assert_eq!(
            decode(&file, FrameFormat::Pgm, Some((3, 4))).unwrap_err(),
            FrameFileError::WrongSize {
                width_px: 4,
                height_px: 3,
                expected_width_px: 3,
                expected_height_px: 4
            }
        );
        // A 12-bit file (maximum 4095) is not read here; `image` scales it to 16 bits.
        let mut twelve = b"P5 2 1 4095\n".to_vec();
        twelve.extend([0x0f, 0xff, 0x00, 0x00]);
        assert_eq!(PgmHeader::read(&twelve), None);
        let read = decode(&twelve, FrameFormat::Pgm, None).expect("decodes");
        assert_eq!(read.pixels(), through_image(&twelve).pixels());
        assert_eq!(&read.pixels()[..], &[65535, 0]);
        // Malformed headers: not read here, and refused by `image` as before.
        for bad in [
            &b"P5 0 3 255\n"[..],
            b"P5 4 3 255",
            b"P5 4 x 255\n",
            b"P2 4 3 255\n",
        ] {
            assert_eq!(PgmHeader::read(bad), None);
            assert!(decode(bad, FrameFormat::Pgm, None).is_err());
        }
    }
}
