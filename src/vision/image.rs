//! Grey frames as the detector sees them: 8- or 16-bit digital numbers (DN), row-major, the
//! top-left pixel first. Integer pixel coordinates are pixel centres: pixel `(u, v)` covers
//! `[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]`, `u` to the right and `v` downwards.
//!
//! A frame keeps the depth it came in: an 8-bit frame is stored a byte a pixel and the detector
//! reads it so (half the memory to pass over, no widening copy); [`GreyImage::pixels`] widens
//! it for the few readers that want 16-bit values.
//!
//! Decoding files (PNG, TIFF, PGM) and turning colour into luma belong to the adapters; the core
//! takes the grey values.

use super::VisionError;

/// Bits per pixel of a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BitDepth {
    /// 0 to 255.
    Eight,
    /// 0 to 65535.
    Sixteen,
}

impl BitDepth {
    /// The largest value a pixel can hold.
    pub fn max_value(self) -> u16 {
        match self {
            BitDepth::Eight => u8::MAX.into(),
            BitDepth::Sixteen => u16::MAX,
        }
    }
}

/// A pixel as the detector reads it: 8 or 16 bits, compared and widened as its value.
pub(crate) trait Pixel: Copy + Ord + Into<u16> + Send + Sync + 'static {
    /// The darkest value.
    const MIN: Self;
    /// The brightest value.
    const MAX: Self;
}

impl Pixel for u8 {
    const MIN: Self = u8::MIN;
    const MAX: Self = u8::MAX;
}

impl Pixel for u16 {
    const MIN: Self = u16::MIN;
    const MAX: Self = u16::MAX;
}

/// A frame's pixels as they are stored, row-major: a byte each for an 8-bit frame, so that an
/// 8-bit camera's frame is neither widened nor read at twice its size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StoredPixels<'a> {
    /// An 8-bit frame's.
    Eight(&'a [u8]),
    /// A 16-bit frame's.
    Sixteen(&'a [u16]),
}

/// A frame's pixels at its depth.
#[derive(Debug, Clone, PartialEq)]
enum Storage {
    Eight(Vec<u8>),
    Sixteen(Vec<u16>),
}

/// A grey frame.
#[derive(Debug, Clone, PartialEq)]
pub struct GreyImage {
    width_px: u32,
    height_px: u32,
    pixels: Storage,
}

impl GreyImage {
    /// A frame from its pixels (row-major). Refuses a pixel count other than `width * height`,
    /// an empty frame, and 8-bit values over 255.
    pub fn new(
        width_px: u32,
        height_px: u32,
        depth: BitDepth,
        pixels: Vec<u16>,
    ) -> Result<Self, VisionError> {
        Self::checked_size(width_px, height_px, pixels.len())?;
        let pixels = match depth {
            BitDepth::Eight => Storage::Eight(
                pixels
                    .iter()
                    .map(|&v| {
                        u8::try_from(v).map_err(|_| VisionError::Degenerate {
                            reason: format!("pixel value {v} does not fit {depth:?} bits"),
                        })
                    })
                    .collect::<Result<_, _>>()?,
            ),
            // Every u16 fits 16 bits.
            BitDepth::Sixteen => Storage::Sixteen(pixels),
        };
        Ok(Self {
            width_px,
            height_px,
            pixels,
        })
    }

    /// An 8-bit frame from its bytes (which fit 8 bits by their type: only the count is checked).
    pub fn from_u8(width_px: u32, height_px: u32, bytes: &[u8]) -> Result<Self, VisionError> {
        Self::from_u8_vec(width_px, height_px, bytes.to_vec())
    }

    /// An 8-bit frame that takes its bytes without a copy.
    pub fn from_u8_vec(width_px: u32, height_px: u32, bytes: Vec<u8>) -> Result<Self, VisionError> {
        Self::checked_size(width_px, height_px, bytes.len())?;
        Ok(Self {
            width_px,
            height_px,
            pixels: Storage::Eight(bytes),
        })
    }

    /// Refuses a pixel count other than `width * height`, and an empty frame.
    fn checked_size(width_px: u32, height_px: u32, count: usize) -> Result<(), VisionError> {
        let expected = width_px as usize * height_px as usize;
        if expected == 0 || count != expected {
            return Err(VisionError::Degenerate {
                reason: format!(
                    "a {width_px} x {height_px} frame needs {expected} pixels, not {count}"
                ),
            });
        }
        Ok(())
    }

    /// Width (px).
    pub fn width_px(&self) -> u32 {
        self.width_px
    }

    /// Height (px).
    pub fn height_px(&self) -> u32 {
        self.height_px
    }

    /// Bits per pixel.
    pub fn depth(&self) -> BitDepth {
        match self.pixels {
            Storage::Eight(_) => BitDepth::Eight,
            Storage::Sixteen(_) => BitDepth::Sixteen,
        }
    }

    /// The pixels, row-major, as 16-bit values (an 8-bit frame's widened into a new buffer).
    pub fn pixels(&self) -> std::borrow::Cow<'_, [u16]> {
        match &self.pixels {
            Storage::Eight(p) => p.iter().map(|&v| u16::from(v)).collect(),
            Storage::Sixteen(p) => std::borrow::Cow::Borrowed(p),
        }
    }

    /// The pixels as they are stored, at the frame's depth.
    pub fn stored(&self) -> StoredPixels<'_> {
        match &self.pixels {
            Storage::Eight(p) => StoredPixels::Eight(p),
            Storage::Sixteen(p) => StoredPixels::Sixteen(p),
        }
    }

    /// The value at column `u`, row `v`.
    pub fn at(&self, u: u32, v: u32) -> u16 {
        let i = v as usize * self.width_px as usize + u as usize;
        match &self.pixels {
            Storage::Eight(p) => p[i].into(),
            Storage::Sixteen(p) => p[i],
        }
    }
}
