//! A camera's thread over libaravis: open by address, configure from `[cameras.source]`,
//! stream, settle each frame's time, hand it on; when the camera goes away, open it again with
//! back-off. Nothing here broadcasts: a GigE Vision camera is opened as a device at its address
//! from the interface that routes to it, a USB3 Vision camera by vendor, model and serial.

use super::TriggerGroups;
use super::state::{AcquiredFrame, SourceState, SourceStatus};
use super::timing::{FrameClock, next_tick_ns, tick_of};
use crate::config::{CameraAddress, CameraSource, PixelFormat, TimestampMode, TriggerMode};
use crate::vision::{BitDepth, GreyImage};
use aravis::glib;
use aravis::glib::prelude::Cast;
use aravis::prelude::*;
use aravis::{Buffer, BufferStatus, Camera, Device, Stream};
use gio;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// Buffers queued on a stream.
const BUFFERS: usize = 8;
/// Longest back-off between attempts to open a camera.
const MAX_BACKOFF: Duration = Duration::from_secs(30);
/// How often the connection is checked (a register read) and PTP's status read.
const CHECK_EVERY: Duration = Duration::from_secs(1);
/// How often `host_fit` latches the device clock, when the camera can.
const LATCH_EVERY: Duration = Duration::from_secs(1);

/// Why a connection ended or could not be made.
#[derive(Debug)]
enum Failure {
    /// The camera refused a setting; the message names the key.
    Refused(String),
    /// The camera could not be reached or went away.
    Lost(String),
}

impl Failure {
    fn lost(what: &str, e: impl std::fmt::Display) -> Failure {
        Failure::Lost(format!("{what}: {e}"))
    }
}

/// An opened, configured camera.
struct Opened {
    camera: Camera,
    exposure_us: f64,
    payload: usize,
    device: String,
    /// `host_fit`: the latch command and the value feature, when the camera has them.
    latch: Option<(&'static str, &'static str, f64)>,
    /// `ptp`: the status feature.
    ptp_status_feature: Option<&'static str>,
}

/// Starts the thread of `state`'s camera, whose frames must be `size` (the installation's).
pub(super) fn spawn(
    state: Arc<SourceState>,
    size: (u32, u32),
    groups: TriggerGroups,
    stop: Arc<AtomicBool>,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    std::thread::Builder::new()
        .name(format!("camera-{}", state.source.camera))
        .spawn(move || run(&state, size, &groups, &stop))
}

/// Opens and configures a camera, then lets it go: `check-config --cameras`.
pub(super) fn probe(source: &CameraSource, size: (u32, u32)) -> Result<String, String> {
    match open(source, size) {
        Ok(o) => Ok(format!(
            "{} at {}: {} x {} px {}, exposure {} µs",
            o.device, source.address, size.0, size.1, source.pixel_format, o.exposure_us
        )),
        Err(Failure::Refused(m) | Failure::Lost(m)) => Err(m),
    }
}

fn run(state: &SourceState, size: (u32, u32), groups: &TriggerGroups, stop: &AtomicBool) {
    let mut backoff = Duration::from_millis(500);
    let mut connected_before = false;
    while !stop.load(Ordering::Acquire) {
        state.update(|d| d.status = SourceStatus::Connecting);
        let failure = match open(&state.source, size) {
            Ok(opened) => {
                if connected_before {
                    state.counters.reconnects.fetch_add(1, Ordering::Relaxed);
                }
                connected_before = true;
                tracing::info!(camera = %state.source.camera, device = %opened.device, "camera connected");
                match stream(state, &opened, groups, stop) {
                    Ok(()) => return,
                    Err(f) => {
                        // Frames flowed: the next attempt starts soon.
                        backoff = Duration::from_millis(500);
                        f
                    }
                }
            }
            Err(f) => f,
        };
        let now = crate::clock::wall_now_ns();
        match failure {
            Failure::Refused(m) => state.error(SourceStatus::Refused, m, now),
            Failure::Lost(m) => state.error(SourceStatus::Disconnected, m, now),
        }
        let until = Instant::now() + backoff;
        while Instant::now() < until && !stop.load(Ordering::Acquire) {
            std::thread::sleep(Duration::from_millis(50));
        }
        backoff = (backoff * 2).min(MAX_BACKOFF);
    }
}

/// The device at the source's address. GigE Vision: from the local address that routes to
/// the camera (a UDP socket connected to it sends nothing), so no interface is scanned.
fn device(address: &CameraAddress) -> Result<Device, Failure> {
    match address {
        CameraAddress::Gige(ip) => {
            let local = std::net::UdpSocket::bind("0.0.0.0:0")
                .and_then(|s| s.connect((*ip, 3956)).map(|()| s))
                .and_then(|s| s.local_addr())
                .map_err(|e| Failure::lost(&format!("no route to {ip}"), e))?;
            let interface = gio::InetAddress::from(local.ip());
            let camera = gio::InetAddress::from(std::net::IpAddr::V4(*ip));
            aravis::GvDevice::new(&interface, &camera)
                .map(|d| d.upcast())
                .map_err(|e| {
                    Failure::Lost(format!(
                        "no GigE Vision camera answers at {ip} (source.address): {e}"
                    ))
                })
        }
        CameraAddress::Usb {
            vendor,
            model,
            serial,
        } => aravis::UvDevice::new(vendor, model, serial)
            .map(|d| d.upcast())
            .map_err(|e| {
                Failure::Lost(format!(
                    "no USB3 Vision camera {vendor} {model} {serial} (source.address): {e}"
                ))
            }),
    }
}

/// One camera is opened at a time: opening parses the camera's GenICam description, and
/// cameras opened at once from several threads were seen to read each other's half-parsed
/// descriptions (an enumeration without its entries) on their first connection.
static OPENING: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Opens the camera and applies every setting, each error naming its key.
fn open(source: &CameraSource, size: (u32, u32)) -> Result<Opened, Failure> {
    let _one_at_a_time = OPENING.lock().unwrap_or_else(|p| p.into_inner());
    let device = device(&source.address)?;
    let camera =
        Camera::with_device(&device).map_err(|e| Failure::lost("cannot open the camera", e))?;
    let refused = |key: &str, e: glib::Error| Failure::Refused(format!("source.{key}: {e}"));
    let vendor = camera
        .vendor_name()
        .map(|s| s.to_string())
        .unwrap_or_default();
    let model = camera
        .model_name()
        .map(|s| s.to_string())
        .unwrap_or_default();
    let device_name = format!("{vendor} {model}").trim().to_owned();
    // Acquisition may run from an earlier session: settings need it stopped.
    let _ = camera.stop_acquisition();

    let formats: Vec<String> = camera
        .dup_available_pixel_formats_as_strings()
        .map(|v| v.iter().map(|s| s.to_string()).collect())
        .unwrap_or_default();
    let wanted = source.pixel_format.name();
    if !formats.is_empty() && !formats.iter().any(|f| f == wanted) {
        return Err(Failure::Refused(format!(
            "source.pixel_format `{wanted}`: the camera offers {}",
            formats.join(", ")
        )));
    }
    camera
        .set_pixel_format_from_string(wanted)
        .map_err(|e| refused("pixel_format", e))?;

    match source.trigger {
        TriggerMode::FreeRun => {
            camera.clear_triggers().map_err(|e| refused("trigger", e))?;
            camera
                .set_frame_rate(source.rate_hz)
                .map_err(|e| refused("rate_hz", e))?;
        }
        TriggerMode::Software => {
            camera
                .set_trigger("Software")
                .map_err(|e| refused("trigger", e))?;
        }
        TriggerMode::Line => {
            camera
                .set_trigger(&source.trigger_line)
                .map_err(|e| refused("trigger_line", e))?;
        }
    }
    if let Some(e) = source.exposure_us {
        camera
            .set_exposure_time(e)
            .map_err(|err| refused("exposure_us", err))?;
    }
    if let Some(g) = source.gain_db {
        camera.set_gain(g).map_err(|e| refused("gain_db", e))?;
    }
    if camera.is_gv_device() {
        match source.packet_size_bytes {
            Some(p) => camera
                .gv_set_packet_size(p as i32)
                .map_err(|e| refused("packet_size_bytes", e))?,
            None => {
                let _ = camera.gv_auto_packet_size();
            }
        }
    }
    for f in &source.features {
        device
            .set_features_from_string(&format!("{}={}", f.name, f.value))
            .map_err(|e| {
                Failure::Refused(format!(
                    "source.features `{}={}`: the camera refused it: {e}",
                    f.name, f.value
                ))
            })?;
    }
    let (_, _, width, height) = camera
        .region()
        .map_err(|e| Failure::lost("cannot read the camera's region", e))?;
    if (width as u32, height as u32) != size {
        return Err(Failure::Refused(format!(
            "the camera gives {width} x {height} px frames but the installation calibrated it at {} x {} px (its width and height): set Width and Height (and OffsetX, OffsetY) in source.features, or calibrate it at this size",
            size.0, size.1
        )));
    }
    let exposure_us = camera
        .exposure_time()
        .map_err(|e| Failure::lost("cannot read the exposure time", e))?;
    let mut ptp_status_feature = None;
    let mut latch = None;
    match source.timestamp {
        TimestampMode::Ptp => {
            let (enable, status) = [("PtpEnable", "PtpStatus"), ("GevIEEE1588", "GevIEEE1588Status")]
                .into_iter()
                .find(|(enable, _)| camera.is_feature_available(enable).unwrap_or(false))
                .ok_or_else(|| {
                    Failure::Refused(
                        "source.timestamp `ptp`: the camera has neither PtpEnable nor GevIEEE1588 (no IEEE 1588 clock); use `host_fit`".into(),
                    )
                })?;
            camera
                .set_boolean(enable, true)
                .map_err(|e| refused("timestamp", e))?;
            ptp_status_feature = Some(status);
        }
        TimestampMode::HostFit => {
            for (command, value, tick_hz) in [
                ("TimestampLatch", "TimestampLatchValue", 1e9),
                ("GevTimestampControlLatch", "GevTimestampValue", 0.0),
            ] {
                if camera.is_feature_available(command).unwrap_or(false)
                    && camera.is_feature_available(value).unwrap_or(false)
                {
                    let hz = if tick_hz > 0.0 {
                        tick_hz
                    } else {
                        camera
                            .integer("GevTimestampTickFrequency")
                            .map(|f| f as f64)
                            .unwrap_or(1e9)
                    };
                    latch = Some((command, value, hz));
                    break;
                }
            }
        }
        TimestampMode::Host => {}
    }
    let payload = camera
        .payload()
        .map_err(|e| Failure::lost("cannot read the payload size", e))? as usize;
    Ok(Opened {
        camera,
        exposure_us,
        payload,
        device: device_name,
        latch,
        ptp_status_feature,
    })
}

/// Reads PTP's status (latching the data set first where the camera needs it).
fn read_ptp_status(camera: &Camera, feature: &str) -> Result<String, glib::Error> {
    if camera
        .is_feature_available("PtpDataSetLatch")
        .unwrap_or(false)
    {
        camera.execute_command("PtpDataSetLatch")?;
    }
    camera.string(feature).map(|s| s.to_string())
}

/// Latches the device clock: `(device_ns, host_ns)` with the host's time read half-way.
fn latch_pair(camera: &Camera, latch: (&str, &str, f64)) -> Option<(i64, i64)> {
    let before = crate::clock::wall_now_ns();
    camera.execute_command(latch.0).ok()?;
    let after = crate::clock::wall_now_ns();
    let ticks = camera.integer(latch.1).ok()?;
    Some((
        (ticks as f64 * 1e9 / latch.2) as i64,
        before + (after - before) / 2,
    ))
}

/// Streams until stopped (`Ok`) or the camera is lost (`Err`).
fn stream(
    state: &SourceState,
    o: &Opened,
    groups: &TriggerGroups,
    stop: &AtomicBool,
) -> Result<(), Failure> {
    let source = &state.source;
    let camera = &o.camera;
    // A camera that has just started may not list its stream channel yet: asked again twice.
    let mut attempt = 0;
    let stream: Stream = loop {
        match camera.create_stream() {
            Ok(stream) => break stream,
            Err(e) if attempt == 2 => return Err(Failure::lost("cannot open the stream", e)),
            Err(_) => {
                attempt += 1;
                std::thread::sleep(Duration::from_millis(200));
            }
        }
    };
    for _ in 0..BUFFERS {
        stream.push_buffer(Buffer::new_allocate(o.payload));
    }
    let mut clock = FrameClock::new(source, o.exposure_us, o.latch.is_some());
    state.update(|d| {
        d.device = Some(o.device.clone());
        d.exposure_us = Some(o.exposure_us);
        d.ptp_status = None;
        d.clock_fit = None;
    });
    camera
        .set_acquisition_mode(aravis::AcquisitionMode::Continuous)
        .map_err(|e| Failure::lost("cannot set continuous acquisition", e))?;
    camera
        .start_acquisition()
        .map_err(|e| Failure::lost("cannot start the acquisition", e))?;
    let period_ns = (1e9 / source.rate_hz) as i64;
    // A camera that should send frames and sends none for this long is taken as lost.
    let silence = match source.trigger {
        TriggerMode::Line => None,
        _ => Some(Duration::from_nanos(period_ns as u64 * 5).max(Duration::from_secs(2))),
    };
    let mut next_tick = next_tick_ns(crate::clock::wall_now_ns(), period_ns);
    let mut last_frame = Instant::now();
    let mut last_check = Instant::now() - CHECK_EVERY;
    let mut last_latch = Instant::now() - LATCH_EVERY;
    let result = loop {
        if stop.load(Ordering::Acquire) {
            break Ok(());
        }
        if last_check.elapsed() >= CHECK_EVERY {
            last_check = Instant::now();
            // A register read: a camera powered off or unplugged fails it.
            if let Err(e) = camera.payload() {
                break Err(Failure::lost("the camera stopped answering", e));
            }
            if let Some(feature) = o.ptp_status_feature {
                match read_ptp_status(camera, feature) {
                    Ok(status) => {
                        clock.set_ptp_status(&status);
                        state.update(|d| d.ptp_status = Some(status));
                    }
                    Err(e) => break Err(Failure::lost("cannot read the PTP status", e)),
                }
            }
        }
        if let Some(latch) = o.latch
            && last_latch.elapsed() >= LATCH_EVERY
        {
            last_latch = Instant::now();
            if let Some((device_ns, host_ns)) = latch_pair(camera, latch) {
                clock.fit.add(device_ns, host_ns);
            }
        }
        let now = crate::clock::wall_now_ns();
        let mut wait_ns = 100_000_000_i64;
        if source.trigger == TriggerMode::Software {
            if now >= next_tick {
                if let Err(e) = camera.software_trigger() {
                    break Err(Failure::lost("the software trigger failed", e));
                }
                next_tick = next_tick_ns(now, period_ns);
            }
            wait_ns = wait_ns.min(next_tick - crate::clock::wall_now_ns()).max(0);
        }
        let Some(buffer) = stream.timeout_pop_buffer((wait_ns / 1000).max(1) as u64) else {
            if let Some(limit) = silence
                && last_frame.elapsed() > limit
            {
                break Err(Failure::Lost(format!(
                    "no frame for {:.1} s",
                    last_frame.elapsed().as_secs_f64()
                )));
            }
            continue;
        };
        last_frame = Instant::now();
        take(state, &buffer, &mut clock, groups, period_ns);
        stream.push_buffer(buffer);
    };
    let _ = camera.stop_acquisition();
    state.update(|d| d.clock_fit = clock.fit.report());
    result
}

/// One buffer: counted, its time settled, its frame handed on.
fn take(
    state: &SourceState,
    buffer: &Buffer,
    clock: &mut FrameClock,
    groups: &TriggerGroups,
    period_ns: i64,
) {
    let source = &state.source;
    let counters = &state.counters;
    if buffer.status() != BufferStatus::Success {
        counters.incomplete.fetch_add(1, Ordering::Relaxed);
        return;
    }
    let arrival_ns = buffer.system_timestamp() as i64;
    let device_ns = buffer.timestamp() as i64;
    let own = clock.frame_time(device_ns, arrival_ns);
    state.update(|d| {
        d.status = SourceStatus::Streaming;
        d.clock_fit = clock.fit.report();
    });
    let own = match own {
        Ok(t) => t,
        Err(super::timing::TimeRefusal::Settling) => {
            counters.settling.fetch_add(1, Ordering::Relaxed);
            return;
        }
        Err(refusal) => {
            counters.refused_time.fetch_add(1, Ordering::Relaxed);
            state.error(SourceStatus::Streaming, refusal.to_string(), arrival_ns);
            return;
        }
    };
    // Frames of one trigger carry one time.
    let time_ns = match source.trigger {
        TriggerMode::FreeRun => own,
        TriggerMode::Software => {
            let half = clock.half_exposure_ns();
            tick_of(own, half, period_ns) + half
        }
        TriggerMode::Line => {
            let window = (period_ns / 2).min((source.tolerance_ms * 1e6) as i64);
            let mut groups = groups.lock().unwrap_or_else(|p| p.into_inner());
            groups
                .entry(source.trigger_group.clone())
                .or_default()
                .instant(own, window)
        }
    };
    let width = buffer.image_width().max(0) as u32;
    let height = buffer.image_height().max(0) as u32;
    let data = buffer.image_data();
    let image = match source.pixel_format {
        PixelFormat::Mono8 => GreyImage::from_u8(width, height, &data),
        _ => {
            let pixels = data
                .chunks_exact(2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]))
                .collect();
            GreyImage::new(width, height, BitDepth::Sixteen, pixels)
        }
    };
    match image {
        Ok(image) => {
            counters.received.fetch_add(1, Ordering::Relaxed);
            state.offer(AcquiredFrame {
                time_ns,
                image,
                arrival_ns,
            });
        }
        Err(e) => {
            counters.incomplete.fetch_add(1, Ordering::Relaxed);
            state.error(
                SourceStatus::Streaming,
                format!("a buffer that is no frame: {e}"),
                arrival_ns,
            );
        }
    }
}
