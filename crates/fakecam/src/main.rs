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
//! * `--stamps FILE`: each frame's device stamp and the host's UTC when the fake made it, one
//!   `device_ns utc_ns` line a frame: the truth a client's timing is measured against.
//! * `--ptp STATUS`: the camera gets an IEEE 1588 clock's features (`PtpEnable`, `PtpStatus`,
//!   `PtpDataSetLatch`); once a client enables it and a frame is made, `PtpStatus` reads
//!   `STATUS` (`Slave`: synchronised; `Listening`, `Faulty`, ...). The stamps are then TAI
//!   unless `--clock` says otherwise.
//!
//! **Run it only inside a network namespace that has only loopback** (`unshare -rn`): the fake
//! answers GigE Vision discovery, and its clients must open it by address. It prints `ready`
//! once it serves, and runs until killed.
//!
//! Two `unsafe` blocks, the project's only ones, give the fake its fill callback (the safe
//! binding does not wrap it): the callback's body, which libaravis calls with a raw buffer,
//! and the call that hands the callback to the fake.

use aravis::glib::object::ObjectType;
use std::ffi::c_void;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

/// The fake's registers (`arvfakecamera.h`).
const REGISTER_WIDTH: u32 = 0x100;
const REGISTER_HEIGHT: u32 = 0x104;
/// The PTP features' registers, where the fake's memory has room.
const REGISTER_PTP_ENABLE: u32 = 0x9000;
const REGISTER_PTP_STATUS: u32 = 0x9004;
/// `PtpStatus`' entries.
const PTP_STATUSES: [&str; 7] = [
    "Disabled",
    "Initializing",
    "Listening",
    "Uncalibrated",
    "Slave",
    "Master",
    "Faulty",
];
/// GenICam pixel formats.
const MONO16: u32 = 0x0110_0007;

/// A frame from a PGM or PNG file, kept as the bytes each pixel format sends, so that making a
/// frame is a copy of rows: the fake's own work stays out of the latency a client measures.
struct Frame {
    width: usize,
    height: usize,
    /// Mono8: the top 8 bits of each value.
    mono8: Vec<u8>,
    /// Mono16: each value little-endian (8-bit files shifted up by 8).
    mono16: Vec<u8>,
}

impl Frame {
    /// A frame of `width` x `height` 16-bit values, row by row.
    fn new(width: usize, height: usize, pixels: &[u16]) -> Frame {
        let pixels = &pixels[..width * height];
        Frame {
            width,
            height,
            mono8: pixels.iter().map(|&v| (v >> 8) as u8).collect(),
            mono16: pixels.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }

    /// Writes the frame into `out`, a buffer of `width` x `height` pixels of `bpp` bytes: the
    /// frame's top-left corner where the sizes differ, zeros beyond it.
    fn copy_into(&self, out: &mut [u8], width: usize, height: usize, bpp: usize) {
        let source = if bpp == 2 { &self.mono16 } else { &self.mono8 };
        let row_bytes = width * bpp;
        let kept = width.min(self.width) * bpp;
        for (v, row) in out.chunks_exact_mut(row_bytes).take(height).enumerate() {
            if v < self.height {
                let from = v * self.width * bpp;
                row[..kept].copy_from_slice(&source[from..from + kept]);
                row[kept..].fill(0);
            } else {
                row.fill(0);
            }
        }
    }
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
    /// `--ptp`: the fake camera, and the status its PTP reaches once enabled.
    ptp: Option<(usize, u32)>,
    /// `--stamps`: where each frame's stamp and the host's time go.
    stamps: Option<std::sync::Mutex<std::io::BufWriter<std::fs::File>>>,
}

/// The PTP features, added to the fake's own GenICam description.
fn ptp_nodes() -> String {
    let entries: String = PTP_STATUSES
        .iter()
        .enumerate()
        .map(|(i, s)| format!("<EnumEntry Name=\"{s}\"><Value>{i}</Value></EnumEntry>"))
        .collect();
    format!(
        r#"<Boolean Name="PtpEnable" NameSpace="Standard"><pValue>PtpEnableRegister</pValue><OnValue>1</OnValue><OffValue>0</OffValue></Boolean>
<IntReg Name="PtpEnableRegister" NameSpace="Custom"><Address>{REGISTER_PTP_ENABLE:#x}</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
<Enumeration Name="PtpStatus" NameSpace="Standard">{entries}<pValue>PtpStatusRegister</pValue></Enumeration>
<IntReg Name="PtpStatusRegister" NameSpace="Custom"><Address>{REGISTER_PTP_STATUS:#x}</Address><Length>4</Length><AccessMode>RO</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
<Command Name="PtpDataSetLatch" NameSpace="Standard"><pValue>PtpDataSetLatchRegister</pValue><CommandValue>1</CommandValue></Command>
<IntReg Name="PtpDataSetLatchRegister" NameSpace="Custom"><Address>0x9008</Address><Length>4</Length><AccessMode>WO</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess></IntReg>
"#
    )
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
    let pixels: Vec<u16> = match info.bit_depth {
        png::BitDepth::Eight => data.iter().map(|&b| u16::from(b) << 8).collect(),
        png::BitDepth::Sixteen => data
            .chunks_exact(2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
            .collect(),
        other => return Err(format!("{}: {other:?} bits a pixel", path.display())),
    };
    let (width, height) = (info.width as usize, info.height as usize);
    Ok(Frame::new(width, height, &pixels))
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
    Ok(Frame::new(width, height, &pixels))
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
        let bpp = if pixel_format == MONO16 { 2 } else { 1 };
        let out = std::slice::from_raw_parts_mut(out, width * height * bpp);
        let frame = &fill.frames[fill.next.fetch_add(1, Ordering::Relaxed) % fill.frames.len()];
        frame.copy_into(out, width, height, bpp);
        // The instant the frame is made: its pixels are in the buffer and the leader packet
        // leaves next. The fake's exposure is instantaneous and its readout free; copying the
        // pixels is the simulation's work, which a loaded host would otherwise count as the
        // camera's latency.
        let now = utc_now_ns();
        if let Some((camera, status)) = fill.ptp {
            let camera = camera as *mut aravis_sys::ArvFakeCamera;
            let mut enabled = 0;
            if aravis_sys::arv_fake_camera_read_register(camera, REGISTER_PTP_ENABLE, &mut enabled)
                != 0
                && enabled != 0
            {
                aravis_sys::arv_fake_camera_write_register(camera, REGISTER_PTP_STATUS, status);
            }
        }
        let stamp = match fill.clock {
            DeviceClock::Utc => now,
            DeviceClock::Boot { drift } => {
                ((now - fill.start_ns) as f64 * (1.0 + drift)) as i64 + 1_000_000_000
            }
            DeviceClock::Tai => now + 37_000_000_000,
        };
        aravis_sys::arv_buffer_set_timestamp(buffer, stamp as u64);
        if let Some(log) = &fill.stamps {
            use std::io::Write;
            let mut log = log.lock().unwrap_or_else(|p| p.into_inner());
            let _ = writeln!(log, "{stamp} {now}").and_then(|()| log.flush());
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
    let mut clock = None;
    let mut ptp = None;
    let mut stamps = None;
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
            "--clock" => clock = Some(value()?),
            "--ptp" => ptp = Some(value()?),
            "--stamps" => stamps = Some(PathBuf::from(value()?)),
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
    let ptp_status = match &ptp {
        Some(status) => Some(
            PTP_STATUSES
                .iter()
                .position(|s| s == status)
                .ok_or_else(|| format!("--ptp `{status}`: one of {}", PTP_STATUSES.join(", ")))?
                as u32,
        ),
        None => None,
    };
    let clock = clock.unwrap_or_else(|| if ptp.is_some() { "tai" } else { "utc" }.to_owned());
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
    // With PTP, the fake's own description plus the PTP features, from a file of this run.
    let description = match ptp_status {
        Some(_) => {
            let (xml, _) = aravis::FakeCamera::new(&serial).genicam_xml();
            let xml = xml.as_str().replacen(
                "</RegisterDescription>",
                &(ptp_nodes() + "</RegisterDescription>"),
                1,
            );
            let path =
                std::env::temp_dir().join(format!("brokenray-fakecam-{}.xml", std::process::id()));
            std::fs::write(&path, xml).map_err(|e| format!("{}: {e}", path.display()))?;
            Some(path.display().to_string())
        }
        None => None,
    };
    let gv = aravis::GvFakeCamera::new_full(Some(&address), Some(&serial), description.as_deref());
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
        ptp: ptp_status.map(|status| (fake.as_ptr() as usize, status)),
        stamps: match stamps {
            Some(path) => Some(std::sync::Mutex::new(std::io::BufWriter::new(
                std::fs::File::create(&path).map_err(|e| format!("{}: {e}", path.display()))?,
            ))),
            None => None,
        },
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
