//! Modbus/TCP (`[[outputs.modbus]]`): a read-only server of a register map, for the PLCs and
//! SCADA systems of a plant. Holding registers (function 3) and input registers (function 4)
//! answer the same map; every write is refused (exception 1, illegal function).
//!
//! Each read is computed from the live state at that moment, the way
//! `GET /api/v1/targets/{name}/compensation` answers it (status judged now, the alarm level in
//! force), so a read never shows an older result than the API.
//!
//! The map ([`FIELDS`], printed by `brokenray modbus-map`): a block of the service at address
//! 0, and a block of [`TARGET_BLOCK`] registers per target at `100 + 100 * index` (addresses
//! from 0, the protocol's own; a tool that counts holding registers from 40001 adds 40001).
//! A 32-bit value takes two registers, the high word first (big-endian words and bytes, `ABCD`).
//! A float is IEEE 754 single precision; one that is not available (no result, no reference)
//! is NaN (`0x7FC0 0x0000`) and its flag in the target's `flags` register is clear.
//! Reads may span fields and blocks; registers between blocks read as 0, and a read past the
//! last target's block is refused (exception 2, illegal data address).

use super::{Counters, Heartbeats, TargetFigures};
use crate::alarms::Level;
use crate::bank::TargetStatus;
use crate::model::TargetId;
use crate::service::Service;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use tokio_modbus::{ExceptionCode, Request, Response};

/// The map's version, in register 0: it changes when a field moves.
pub const MAP_VERSION: u16 = 1;
/// Where target 0's block starts.
pub const FIRST_TARGET: u16 = 100;
/// The distance between two targets' blocks.
pub const TARGET_STRIDE: u16 = 100;
/// The registers of a target's block that hold something.
pub const TARGET_BLOCK: u16 = 60;
/// Most targets the map addresses.
pub const MAX_TARGETS: usize = 600;
/// Most registers one read may ask for (the protocol's limit).
const MAX_READ: u16 = 125;
/// Most clients at once; more are refused at connection.
const MAX_CLIENTS: usize = 16;

/// What a field holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FieldType {
    /// One register.
    U16,
    /// Two registers, high word first.
    U32,
    /// Two registers, IEEE 754 single, high word first.
    F32,
}

impl FieldType {
    /// Registers it takes.
    pub fn words(self) -> u16 {
        match self {
            FieldType::U16 => 1,
            FieldType::U32 | FieldType::F32 => 2,
        }
    }

    /// Its name in the printed map.
    pub fn name(self) -> &'static str {
        match self {
            FieldType::U16 => "u16",
            FieldType::U32 => "u32",
            FieldType::F32 => "f32",
        }
    }
}

/// Which value a field carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Value {
    /// The map's version.
    MapVersion,
    /// How many targets the map has.
    TargetCount,
    /// Seconds the outputs have run: a counter that moves every second while the service runs.
    ServiceHeartbeat,
    /// The target's status code.
    Status,
    /// The target's alarm level.
    Alarm,
    /// Results of the target published since the start: moves with every new result.
    ResultCounter,
    /// Seconds from the newest result to now.
    AgeS,
    /// Bit 0: a result; bit 1: a deformation (a reference is set).
    Flags,
    /// The newest result's time, whole seconds since 1970 (UTC).
    TimeS,
    /// Its milliseconds.
    TimeMs,
    /// The deformation's rotation vector, axis 0..3 (arc-seconds).
    DeformationRotation(usize),
    /// The deformation's translation, axis 0..3 (mm).
    DeformationTranslation(usize),
    /// The deformation's rotation sigma, axis 0..3 (arc-seconds).
    DeformationRotationSigma(usize),
    /// The deformation's translation sigma, axis 0..3 (mm).
    DeformationTranslationSigma(usize),
    /// The correction's rotation vector, axis 0..3 (arc-seconds).
    CorrectionRotation(usize),
    /// The correction's translation, axis 0..3 (mm).
    CorrectionTranslation(usize),
    /// The correction's rotation sigma, axis 0..3 (arc-seconds).
    CorrectionRotationSigma(usize),
    /// The correction's translation sigma, axis 0..3 (mm).
    CorrectionTranslationSigma(usize),
}

/// One field of the map: its offset in its block, type, name, unit and meaning.
#[derive(Debug, Clone, Copy)]
pub struct Field {
    /// Offset in its block (the service's at 0, or a target's).
    pub offset: u16,
    /// Its type.
    pub kind: FieldType,
    /// What it carries.
    pub value: Value,
    /// Its name in the printed map.
    pub name: &'static str,
    /// Its unit.
    pub unit: &'static str,
    /// What it means.
    pub meaning: &'static str,
}

const fn f(
    offset: u16,
    kind: FieldType,
    value: Value,
    name: &'static str,
    unit: &'static str,
    meaning: &'static str,
) -> Field {
    Field {
        offset,
        kind,
        value,
        name,
        unit,
        meaning,
    }
}

use FieldType::{F32, U16, U32};
use Value as V;

/// The service's block, at address 0.
pub const SERVICE_FIELDS: &[Field] = &[
    f(
        0,
        U16,
        V::MapVersion,
        "map_version",
        "",
        "the map's version (1)",
    ),
    f(
        1,
        U16,
        V::TargetCount,
        "targets",
        "",
        "how many targets have a block",
    ),
    f(
        2,
        U32,
        V::ServiceHeartbeat,
        "heartbeat",
        "s",
        "counts seconds while the service runs; a counter that stops says the service stopped",
    ),
];

/// A target's block, at `100 + 100 * index`.
pub const FIELDS: &[Field] = &[
    f(
        0,
        U16,
        V::Status,
        "status",
        "",
        "0 initializing, 1 ok, 2 stale, 3 degraded, 4 predicted",
    ),
    f(
        1,
        U16,
        V::Alarm,
        "alarm",
        "",
        "0 none, 1 warn, 2 alarm (the level in force)",
    ),
    f(
        2,
        U32,
        V::ResultCounter,
        "result_counter",
        "",
        "counts the results published; moves with every new result",
    ),
    f(
        4,
        F32,
        V::AgeS,
        "age_s",
        "s",
        "from the newest result's time to now",
    ),
    f(
        6,
        U16,
        V::Flags,
        "flags",
        "",
        "bit 0: a result; bit 1: a deformation (a reference is set)",
    ),
    f(
        8,
        U32,
        V::TimeS,
        "time_s",
        "s",
        "the newest result's time, seconds since 1970-01-01 UTC",
    ),
    f(10, U16, V::TimeMs, "time_ms", "ms", "its milliseconds"),
    f(
        12,
        F32,
        V::DeformationRotation(0),
        "deformation_rx",
        "arcsec",
        "deformation, rotation vector x",
    ),
    f(
        14,
        F32,
        V::DeformationRotation(1),
        "deformation_ry",
        "arcsec",
        "deformation, rotation vector y",
    ),
    f(
        16,
        F32,
        V::DeformationRotation(2),
        "deformation_rz",
        "arcsec",
        "deformation, rotation vector z",
    ),
    f(
        18,
        F32,
        V::DeformationTranslation(0),
        "deformation_tx",
        "mm",
        "deformation, translation x",
    ),
    f(
        20,
        F32,
        V::DeformationTranslation(1),
        "deformation_ty",
        "mm",
        "deformation, translation y",
    ),
    f(
        22,
        F32,
        V::DeformationTranslation(2),
        "deformation_tz",
        "mm",
        "deformation, translation z",
    ),
    f(
        24,
        F32,
        V::DeformationRotationSigma(0),
        "deformation_sigma_rx",
        "arcsec",
        "its standard deviation",
    ),
    f(
        26,
        F32,
        V::DeformationRotationSigma(1),
        "deformation_sigma_ry",
        "arcsec",
        "its standard deviation",
    ),
    f(
        28,
        F32,
        V::DeformationRotationSigma(2),
        "deformation_sigma_rz",
        "arcsec",
        "its standard deviation",
    ),
    f(
        30,
        F32,
        V::DeformationTranslationSigma(0),
        "deformation_sigma_tx",
        "mm",
        "its standard deviation",
    ),
    f(
        32,
        F32,
        V::DeformationTranslationSigma(1),
        "deformation_sigma_ty",
        "mm",
        "its standard deviation",
    ),
    f(
        34,
        F32,
        V::DeformationTranslationSigma(2),
        "deformation_sigma_tz",
        "mm",
        "its standard deviation",
    ),
    f(
        36,
        F32,
        V::CorrectionRotation(0),
        "correction_rx",
        "arcsec",
        "correction (what a device applies), rotation vector x",
    ),
    f(
        38,
        F32,
        V::CorrectionRotation(1),
        "correction_ry",
        "arcsec",
        "correction, rotation vector y",
    ),
    f(
        40,
        F32,
        V::CorrectionRotation(2),
        "correction_rz",
        "arcsec",
        "correction, rotation vector z",
    ),
    f(
        42,
        F32,
        V::CorrectionTranslation(0),
        "correction_tx",
        "mm",
        "correction, translation x",
    ),
    f(
        44,
        F32,
        V::CorrectionTranslation(1),
        "correction_ty",
        "mm",
        "correction, translation y",
    ),
    f(
        46,
        F32,
        V::CorrectionTranslation(2),
        "correction_tz",
        "mm",
        "correction, translation z",
    ),
    f(
        48,
        F32,
        V::CorrectionRotationSigma(0),
        "correction_sigma_rx",
        "arcsec",
        "its standard deviation",
    ),
    f(
        50,
        F32,
        V::CorrectionRotationSigma(1),
        "correction_sigma_ry",
        "arcsec",
        "its standard deviation",
    ),
    f(
        52,
        F32,
        V::CorrectionRotationSigma(2),
        "correction_sigma_rz",
        "arcsec",
        "its standard deviation",
    ),
    f(
        54,
        F32,
        V::CorrectionTranslationSigma(0),
        "correction_sigma_tx",
        "mm",
        "its standard deviation",
    ),
    f(
        56,
        F32,
        V::CorrectionTranslationSigma(1),
        "correction_sigma_ty",
        "mm",
        "its standard deviation",
    ),
    f(
        58,
        F32,
        V::CorrectionTranslationSigma(2),
        "correction_sigma_tz",
        "mm",
        "its standard deviation",
    ),
];

/// The status code of the map.
pub fn status_code(status: TargetStatus) -> u16 {
    match status {
        TargetStatus::Initializing => 0,
        TargetStatus::Ok => 1,
        TargetStatus::Stale => 2,
        TargetStatus::Degraded => 3,
        TargetStatus::Predicted => 4,
    }
}

/// The alarm code of the map.
pub fn alarm_code(level: Level) -> u16 {
    match level {
        Level::None => 0,
        Level::Warn => 1,
        Level::Alarm => 2,
    }
}

/// The map as text: one line per register field, with absolute addresses for `targets`.
pub fn describe(targets: &[String]) -> String {
    let mut out = String::from(
        "# brokenray Modbus/TCP register map (version 1). Holding (function 3) and input (function 4)\n\
         # registers answer the same map; addresses from 0; 32-bit values high word first (ABCD);\n\
         # f32 = IEEE 754 single, NaN when not available.\n\
         address\ttype\tname\tunit\tmeaning\n",
    );
    for field in SERVICE_FIELDS {
        out.push_str(&format!(
            "{}\t{}\tservice.{}\t{}\t{}\n",
            field.offset,
            field.kind.name(),
            field.name,
            field.unit,
            field.meaning
        ));
    }
    for (i, name) in targets.iter().enumerate().take(MAX_TARGETS) {
        let base = block_start(i);
        for field in FIELDS {
            out.push_str(&format!(
                "{}\t{}\t{name}.{}\t{}\t{}\n",
                base + u32::from(field.offset),
                field.kind.name(),
                field.name,
                field.unit,
                field.meaning
            ));
        }
    }
    out
}

/// Where target `i`'s block starts.
pub fn block_start(i: usize) -> u32 {
    u32::from(FIRST_TARGET) + u32::from(TARGET_STRIDE) * i as u32
}

/// Writes `field`'s value at its offset into `block`.
fn put(block: &mut [u16], field: &Field, value: f64) {
    let at = usize::from(field.offset);
    match field.kind {
        FieldType::U16 => block[at] = value as u16,
        FieldType::U32 => {
            let v = value as u32;
            block[at] = (v >> 16) as u16;
            block[at + 1] = v as u16;
        }
        FieldType::F32 => {
            let v = (value as f32).to_bits();
            block[at] = (v >> 16) as u16;
            block[at + 1] = v as u16;
        }
    }
}

/// A target's block from its figures and its result counter.
pub fn target_block(figures: Option<&TargetFigures>, results: u32) -> [u16; TARGET_BLOCK as usize] {
    let mut block = [0u16; TARGET_BLOCK as usize];
    let axis = |m: Option<crate::deformation::SmallMotion>,
                pick: fn(&crate::deformation::SmallMotion) -> [f64; 3],
                i: usize| { m.map_or(f64::NAN, |m| pick(&m)[i]) };
    for field in FIELDS {
        let d = figures.and_then(|f| f.deformation);
        let c = figures.and_then(|f| f.correction);
        let value = match field.value {
            V::Status => figures.map_or(0, |f| status_code(f.status)).into(),
            V::Alarm => figures.map_or(0, |f| alarm_code(f.alarm)).into(),
            V::ResultCounter => results.into(),
            V::AgeS => figures.map_or(f64::NAN, |f| f.age_s),
            V::Flags => f64::from(u16::from(figures.is_some()) | (u16::from(d.is_some()) << 1)),
            V::TimeS => figures.map_or(0.0, |f| f.time_ns.div_euclid(1_000_000_000) as f64),
            V::TimeMs => figures.map_or(0.0, |f| {
                (f.time_ns.rem_euclid(1_000_000_000) / 1_000_000) as f64
            }),
            V::DeformationRotation(i) => axis(d, |m| m.rotation_arcsec, i),
            V::DeformationTranslation(i) => axis(d, |m| m.translation_mm, i),
            V::DeformationRotationSigma(i) => axis(d, |m| m.sigmas.rotation_arcsec, i),
            V::DeformationTranslationSigma(i) => axis(d, |m| m.sigmas.translation_mm, i),
            V::CorrectionRotation(i) => axis(c, |m| m.rotation_arcsec, i),
            V::CorrectionTranslation(i) => axis(c, |m| m.translation_mm, i),
            V::CorrectionRotationSigma(i) => axis(c, |m| m.sigmas.rotation_arcsec, i),
            V::CorrectionTranslationSigma(i) => axis(c, |m| m.sigmas.translation_mm, i),
            V::MapVersion | V::TargetCount | V::ServiceHeartbeat => 0.0,
        };
        put(&mut block, field, value);
    }
    block
}

/// The registers `[start, start + count)` read now.
pub fn read(
    service: &Service,
    heartbeats: &Heartbeats,
    start: u16,
    count: u16,
) -> Result<Vec<u16>, ExceptionCode> {
    if count == 0 || count > MAX_READ {
        return Err(ExceptionCode::IllegalDataValue);
    }
    let n_targets = service.installation().model.targets.len().min(MAX_TARGETS);
    let end = u32::from(start) + u32::from(count);
    let last = if n_targets == 0 {
        u32::from(FIRST_TARGET)
    } else {
        block_start(n_targets - 1) + u32::from(TARGET_BLOCK)
    };
    if end > last {
        return Err(ExceptionCode::IllegalDataAddress);
    }
    let mut out = vec![0u16; usize::from(count)];
    // The service's block.
    let mut service_block = [0u16; 4];
    for field in SERVICE_FIELDS {
        let value = match field.value {
            V::MapVersion => f64::from(MAP_VERSION),
            V::TargetCount => n_targets as f64,
            V::ServiceHeartbeat => f64::from(heartbeats.service.load(Relaxed)),
            _ => 0.0,
        };
        put(&mut service_block, field, value);
    }
    copy_block(&mut out, u32::from(start), 0, &service_block);
    for i in 0..n_targets {
        let base = block_start(i);
        if base >= end || base + u32::from(TARGET_BLOCK) <= u32::from(start) {
            continue;
        }
        let figures = TargetFigures::live(service, TargetId(i));
        let results = heartbeats.targets.get(i).map_or(0, |h| h.load(Relaxed));
        copy_block(
            &mut out,
            u32::from(start),
            base,
            &target_block(figures.as_ref(), results),
        );
    }
    Ok(out)
}

/// Copies the part of `block` (at address `base`) that falls in `out` (at address `start`).
fn copy_block(out: &mut [u16], start: u32, base: u32, block: &[u16]) {
    for (k, word) in block.iter().enumerate() {
        let address = base + k as u32;
        if let Some(slot) = address
            .checked_sub(start)
            .and_then(|o| out.get_mut(o as usize))
        {
            *slot = *word;
        }
    }
}

/// One client's view of the map.
struct MapService {
    service: Service,
    heartbeats: Arc<Heartbeats>,
    counters: Arc<Counters>,
    _slot: tokio::sync::OwnedSemaphorePermit,
}

impl Drop for MapService {
    fn drop(&mut self) {
        self.counters.clients.fetch_sub(1, Relaxed);
    }
}

impl tokio_modbus::server::Service for MapService {
    type Request = Request<'static>;
    type Response = Response;
    type Exception = ExceptionCode;
    type Future = std::future::Ready<Result<Response, ExceptionCode>>;

    fn call(&self, request: Self::Request) -> Self::Future {
        let answer = match request {
            Request::ReadHoldingRegisters(start, count) => {
                read(&self.service, &self.heartbeats, start, count)
                    .map(Response::ReadHoldingRegisters)
            }
            Request::ReadInputRegisters(start, count) => {
                read(&self.service, &self.heartbeats, start, count)
                    .map(Response::ReadInputRegisters)
            }
            _ => Err(ExceptionCode::IllegalFunction),
        };
        if answer.is_ok() {
            self.counters.sent(1, self.service.now_ns());
        }
        std::future::ready(answer)
    }
}

/// Serves the map on `listener` until shutdown.
pub(super) fn spawn(
    service: Service,
    listener: tokio::net::TcpListener,
    heartbeats: Arc<Heartbeats>,
    counters: Arc<Counters>,
) -> tokio::task::JoinHandle<()> {
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CLIENTS));
    counters.set_connected(true);
    let mut stop = service.stopping();
    service.clone().spawn_watched("modbus output", async move {
        let server = tokio_modbus::server::tcp::Server::new(listener);
        let on_connected = |stream: tokio::net::TcpStream, peer: std::net::SocketAddr| {
            let permit = Arc::clone(&slots).try_acquire_owned();
            let service = service.clone();
            let heartbeats = Arc::clone(&heartbeats);
            let counters = Arc::clone(&counters);
            async move {
                let Ok(slot) = permit else {
                    counters.error(
                        service.now_ns(),
                        format!("a client at {peer} was refused: {MAX_CLIENTS} are connected"),
                    );
                    return Ok(None);
                };
                counters.clients.fetch_add(1, Relaxed);
                Ok(Some((
                    MapService {
                        service,
                        heartbeats,
                        counters,
                        _slot: slot,
                    },
                    stream,
                )))
            }
        };
        let errors = Arc::clone(&counters);
        let clock = service.clone();
        let on_error = move |e: std::io::Error| {
            errors.error(clock.now_ns(), format!("a client's connection failed: {e}"));
        };
        let stopping = async move {
            let _ = stop.wait_for(|s| *s).await;
        };
        if let Err(e) = server.serve_until(&on_connected, on_error, stopping).await {
            counters.error(service.now_ns(), format!("the server stopped: {e}"));
            tracing::error!(error = %e, "the Modbus output stopped");
        }
        counters.set_connected(false);
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fields_tile_the_block_without_overlap() {
        for fields in [SERVICE_FIELDS, FIELDS] {
            let mut used = std::collections::BTreeSet::new();
            for field in fields {
                for w in 0..field.kind.words() {
                    assert!(used.insert(field.offset + w), "{} overlaps", field.name);
                }
            }
        }
        let end = FIELDS.iter().map(|f| f.offset + f.kind.words()).max();
        assert_eq!(end, Some(TARGET_BLOCK));
        const { assert!(TARGET_BLOCK <= TARGET_STRIDE) };
        assert!(block_start(MAX_TARGETS - 1) + u32::from(TARGET_BLOCK) <= 65_536);
    }

    #[test]
    fn a_float_is_high_word_first_and_absent_values_are_nan() {
        let block = target_block(None, 7);
        // result_counter at 2..4, high word first.
        assert_eq!(&block[2..4], &[0, 7]);
        let age = f32::from_bits((u32::from(block[4]) << 16) | u32::from(block[5]));
        assert!(age.is_nan());
        assert_eq!(block[6], 0, "no flags without a result");
        let one = (1.5f32).to_bits();
        let mut b = [0u16; 2];
        put(&mut b, &f(0, F32, V::AgeS, "", "", ""), 1.5);
        assert_eq!(b, [(one >> 16) as u16, one as u16]);
    }
}
