//! `brokenray-fakecam`: libaravis' fake GigE Vision camera, serving frames read from PGM files
//! instead of its test pattern, for brokenray's tests and rehearsals without hardware.
//!
//! ```text
//! brokenray-fakecam --address 127.0.0.2 --frames DIR [--serial S] [--clock utc|boot|tai]
//!                   [--drift-ppm X] [--loss RATIO] [--width W --height H]
//! ```
//!
//! * Every `*.pgm` and `*.png` in `DIR` (grey, 8 or 16 bit: what `brokenray simulate --emit
//!   frames` writes for a camera), in name order, served in turn,
//!   one per buffer, in the pixel format the client set (Mono8 or Mono16, converted by shifting
//!   8 bits).
//! * `--clock`: the device's stamps. `utc` (the fake's own: the host's UTC), `boot` (nanoseconds
//!   since this program started, running `--drift-ppm` fast: a camera without PTP), `tai` (UTC
//!   plus 37 s: a camera synchronised by PTP).
//! * `--loss`: the share of stream packets dropped (incomplete buffers).
//! * `--width`, `--height`: the size the camera starts with (default: the frames').
//!
//! **Run it only inside a network namespace that has only loopback** (`unshare -rn`): the fake
//! answers GigE Vision discovery, and its clients must open it by address. It prints `ready`
//! once it serves, and runs until killed.
//!
//! The one `unsafe` block gives the fake its fill callback (the safe binding does not wrap it).

use aravis::glib::object::ObjectType;
use std::ffi::c_void;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

/// The fake's registers (`arvfakecamera.h`).
const REGISTER_WIDTH: u32 = 0x100;
const REGISTER_HEIGHT: u32 = 0x104;
/// GenICam pixel formats.
const MONO16: u32 = 0x0110_0007;

/// A frame from a PGM file.
struct Frame {
    width: usize,
    height: usize,
    /// 16-bit values (8-bit files shifted up by 8).
    pixels: Vec<u16>,
}

/// What the device stamps.
#[derive(Clone, Copy, PartialEq)]
enum DeviceClock {
    Utc,
    Boot { drift: f64 },
    Tai,
}

/// What the callback serves.
struct Fill {
    frames: Vec<Frame>,
    next: AtomicUsize,
    clock: DeviceClock,
    start_ns: i64,
}

fn utc_now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as i64)
}

fn read_png(path: &std::path::Path) -> Result<Frame, String> {
    let file = std::fs::File::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder
        .read_info()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    let mut data = vec![0; reader.output_buffer_size().unwrap_or(0)];
    let info = reader
        .next_frame(&mut data)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    if info.color_type != png::ColorType::Grayscale {
        return Err(format!("{}: not a grey PNG", path.display()));
    }
    let data = &data[..info.buffer_size()];
    let pixels = match info.bit_depth {
        png::BitDepth::Eight => data.iter().map(|&b| u16::from(b) << 8).collect(),
        png::BitDepth::Sixteen => data
            .chunks_exact(2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
            .collect(),
        other => return Err(format!("{}: {other:?} bits a pixel", path.display())),
    };
    Ok(Frame {
        width: info.width as usize,
        height: info.height as usize,
        pixels,
    })
}

fn read_pgm(path: &std::path::Path) -> Result<Frame, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while at < bytes.len() && bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        if at < bytes.len() && bytes[at] == b'#' {
            while at < bytes.len() && bytes[at] != b'\n' {
                at += 1;
            }
            continue;
        }
        let start = at;
        while at < bytes.len() && !bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        if start == at {
            return Err(format!("{}: a short PGM header", path.display()));
        }
        fields.push(String::from_utf8_lossy(&bytes[start..at]).into_owned());
    }
    at += 1;
    let number = |i: usize| -> Result<usize, String> {
        fields[i]
            .parse()
            .map_err(|_| format!("{}: `{}` is not a number", path.display(), fields[i]))
    };
    if fields[0] != "P5" {
        return Err(format!("{}: not a binary PGM (P5)", path.display()));
    }
    let (width, height, max) = (number(1)?, number(2)?, number(3)?);
    let data = &bytes[at.min(bytes.len())..];
    let pixels: Vec<u16> = if max > 255 {
        data.chunks_exact(2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
            .collect()
    } else {
        data.iter().map(|&b| u16::from(b) << 8).collect()
    };
    if pixels.len() < width * height {
        return Err(format!(
            "{}: fewer pixels than {width} x {height}",
            path.display()
        ));
    }
    Ok(Frame {
        width,
        height,
        pixels,
    })
}

/// Fills a buffer with the next frame and stamps it.
///
/// # Safety
///
/// Called by libaravis with a buffer being filled, `data` the `Fill` leaked in `main`.
unsafe extern "C" fn fill(
    buffer: *mut aravis_sys::ArvBuffer,
    data: *mut c_void,
    _exposure_time_us: u32,
    _gain: u32,
    pixel_format: u32,
) {
    // SAFETY: `data` is the `Fill` leaked in `main`, alive for the program; the buffer is the
    // one being filled, whose data holds at least its width x height x bytes a pixel (the fake
    // checks the payload before calling).
    unsafe {
        let fill = &*(data as *const Fill);
        let width = aravis_sys::arv_buffer_get_image_width(buffer).max(0) as usize;
        let height = aravis_sys::arv_buffer_get_image_height(buffer).max(0) as usize;
        let mut size = 0;
        let out = aravis_sys::arv_buffer_get_data(buffer, &mut size);
        let sixteen = pixel_format == MONO16;
        let bpp = if sixteen { 2 } else { 1 };
        let out = std::slice::from_raw_parts_mut(out, width * height * bpp);
        let frame = &fill.frames[fill.next.fetch_add(1, Ordering::Relaxed) % fill.frames.len()];
        for v in 0..height {
            for u in 0..width {
                let value = if u < frame.width && v < frame.height {
                    frame.pixels[v * frame.width + u]
                } else {
                    0
                };
                let i = v * width + u;
                if sixteen {
                    out[2 * i..2 * i + 2].copy_from_slice(&value.to_le_bytes());
                } else {
                    out[i] = (value >> 8) as u8;
                }
            }
        }
        let now = utc_now_ns();
        let stamp = match fill.clock {
            DeviceClock::Utc => None,
            DeviceClock::Boot { drift } => {
                Some(((now - fill.start_ns) as f64 * (1.0 + drift)) as i64 + 1_000_000_000)
            }
            DeviceClock::Tai => Some(now + 37_000_000_000),
        };
        if let Some(stamp) = stamp {
            aravis_sys::arv_buffer_set_timestamp(buffer, stamp as u64);
        }
    }
}

fn main() {
    if let Err(e) = run() {
        eprintln!("brokenray-fakecam: {e}");
        std::process::exit(2);
    }
}

fn run() -> Result<(), String> {
    let mut args = std::env::args().skip(1);
    let mut address = None;
    let mut frames_dir = None;
    let mut serial = "FAKE0".to_owned();
    let mut clock = "utc".to_owned();
    let mut drift_ppm = 0.0;
    let mut loss = 0.0;
    let mut width = None;
    let mut height = None;
    while let Some(flag) = args.next() {
        let mut value = || args.next().ok_or_else(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--address" => address = Some(value()?),
            "--frames" => frames_dir = Some(PathBuf::from(value()?)),
            "--serial" => serial = value()?,
            "--clock" => clock = value()?,
            "--drift-ppm" => drift_ppm = value()?.parse().map_err(|_| "--drift-ppm: a number")?,
            "--loss" => loss = value()?.parse().map_err(|_| "--loss: a number")?,
            "--width" => width = Some(value()?.parse::<u32>().map_err(|_| "--width: a number")?),
            "--height" => height = Some(value()?.parse::<u32>().map_err(|_| "--height: a number")?),
            other => return Err(format!("unknown argument `{other}`")),
        }
    }
    let address = address.ok_or("--address is required")?;
    let dir = frames_dir.ok_or("--frames is required")?;
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map_err(|e| format!("{}: {e}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "pgm" || x == "png"))
        .collect();
    paths.sort();
    let frames = paths
        .iter()
        .map(|p| {
            if p.extension().is_some_and(|x| x == "png") {
                read_png(p)
            } else {
                read_pgm(p)
            }
        })
        .collect::<Result<Vec<_>, _>>()?;
    let first = frames.first().ok_or("no .pgm or .png frames in --frames")?;
    let clock = match clock.as_str() {
        "utc" => DeviceClock::Utc,
        "boot" => DeviceClock::Boot {
            drift: drift_ppm * 1e-6,
        },
        "tai" => DeviceClock::Tai,
        other => return Err(format!("--clock `{other}`: utc, boot or tai")),
    };
    let (w, h) = (
        width.unwrap_or(first.width as u32),
        height.unwrap_or(first.height as u32),
    );
    let gv = aravis::GvFakeCamera::new(Some(&address), Some(&serial));
    let fake = gv.fake_camera().ok_or("the fake camera did not start")?;
    fake.write_register(REGISTER_WIDTH, w);
    fake.write_register(REGISTER_HEIGHT, h);
    if loss > 0.0 {
        gv.set_gvsp_lost_ratio(loss);
    }
    let fill_data = Box::leak(Box::new(Fill {
        frames,
        next: AtomicUsize::new(0),
        clock,
        start_ns: utc_now_ns(),
    }));
    // SAFETY: the fake camera outlives nothing here (the program ends with it), the data is
    // leaked so it lives as long as the callback may run, and `fill` has the callback's type.
    unsafe {
        aravis_sys::arv_fake_camera_set_fill_pattern(
            fake.as_ptr(),
            Some(fill),
            fill_data as *mut Fill as *mut c_void,
        );
    }
    if !gv.is_running() {
        return Err(format!("the fake camera cannot serve at {address}"));
    }
    println!("ready");
    loop {
        std::thread::park();
    }
}
