//! Grey frames as the detector sees them: 8- or 16-bit digital numbers (DN), row-major, the
//! top-left pixel first. Integer pixel coordinates are pixel centres: pixel `(u, v)` covers
//! `[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]`, `u` to the right and `v` downwards.
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

/// A grey frame.
#[derive(Debug, Clone, PartialEq)]
pub struct GreyImage {
    width_px: u32,
    height_px: u32,
    depth: BitDepth,
    pixels: Vec<u16>,
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
        // Every u16 fits 16 bits: only 8-bit frames need the look.
        if depth == BitDepth::Eight
            && let Some(v) = pixels.iter().find(|&&v| v > depth.max_value())
        {
            return Err(VisionError::Degenerate {
                reason: format!("pixel value {v} does not fit {depth:?} bits"),
            });
        }
        Ok(Self {
            width_px,
            height_px,
            depth,
            pixels,
        })
    }

    /// An 8-bit frame from its bytes (which fit 8 bits by their type: only the count is checked).
    pub fn from_u8(width_px: u32, height_px: u32, bytes: &[u8]) -> Result<Self, VisionError> {
        Self::checked_size(width_px, height_px, bytes.len())?;
        Ok(Self {
            width_px,
            height_px,
            depth: BitDepth::Eight,
            pixels: bytes.iter().map(|&b| u16::from(b)).collect(),
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
        self.depth
    }

    /// The pixels, row-major.
    pub fn pixels(&self) -> &[u16] {
        &self.pixels
    }

    /// The value at column `u`, row `v`.
    pub fn at(&self, u: u32, v: u32) -> u16 {
        self.pixels[v as usize * self.width_px as usize + u as usize]
    }
}
