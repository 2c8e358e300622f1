//! The upload's wire format: a JSON document, compressed with zstd
//! (`Content-Encoding: zstd`), posted to `POST /api/v1/sites/{site}/sync`.

use crate::store::outbox::{OutboxBatch, Registry, TableRows, Tier};
pub use crate::store::outbox::{RawRequest, RequestedRows};
use serde::{Deserialize, Serialize};

/// The zstd level of uploads: a satellite link costs more than the site's cores.
pub const ZSTD_LEVEL: i32 = 9;

/// One upload: the site's identity and state, and at most one batch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyncRequest {
    /// The site's outbox (random, made with its file).
    pub outbox_id: String,
    /// The outbox's generation (absent: its first, named by `outbox_id`). A restored copy of
    /// a site's database uploads in a generation of its own.
    #[serde(default)]
    pub generation: Option<String>,
    /// The generations it descends from, the nearest first.
    #[serde(default)]
    pub lineage: Vec<String>,
    /// The site's newest commit when the upload was read: a batch never goes past it, and it
    /// never goes back within a generation. Required with a batch.
    #[serde(default)]
    pub head_seq: Option<i64>,
    /// The names behind the ids of the rows.
    pub registry: Registry,
    /// The rows of one tier; absent in a report of state alone.
    #[serde(default)]
    pub batch: Option<WireBatch>,
    /// The site's current state.
    #[serde(default)]
    pub status: Option<SiteStatus>,
    /// What the site has still to send, per tier.
    #[serde(default)]
    pub backlog: Vec<TierBacklog>,
    /// Raw rows of a period the centre asked for, outside the commit stream; never with a
    /// batch.
    #[serde(default)]
    pub requested: Option<RequestedRows>,
}

/// A batch on the wire.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WireBatch {
    /// The tier.
    pub tier: Tier,
    /// The commit after which it starts (`None`: the outbox's start).
    pub after_seq: Option<i64>,
    /// The last commit it covers.
    pub upto_seq: i64,
    /// True when it holds a part of its one commit `upto_seq` and more parts follow (absent:
    /// false); the centre applies its rows and acknowledges nothing new.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub partial: bool,
    /// When the site made the commit `upto_seq` (its clock, ns).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub upto_stamp_ns: Option<i64>,
    /// The rows, per table.
    pub tables: Vec<TableRows>,
}

impl From<OutboxBatch> for WireBatch {
    fn from(b: OutboxBatch) -> Self {
        WireBatch {
            tier: b.tier,
            after_seq: (b.after_seq != i64::MIN).then_some(b.after_seq),
            upto_seq: b.upto_seq,
            partial: b.partial,
            upto_stamp_ns: b.upto_stamp_ns,
            tables: b.tables,
        }
    }
}

impl From<WireBatch> for OutboxBatch {
    fn from(b: WireBatch) -> Self {
        OutboxBatch {
            tier: b.tier,
            after_seq: b.after_seq.unwrap_or(i64::MIN),
            upto_seq: b.upto_seq,
            partial: b.partial,
            upto_stamp_ns: b.upto_stamp_ns,
            tables: b.tables,
        }
    }
}

/// What a centre reads of one upload at most: the upload's JSON once decompressed, and its
/// values (counted as [`json_values`] counts them). A site keeps its uploads within both.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct UploadLimits {
    /// Bytes of JSON.
    pub json_bytes: u64,
    /// Values.
    pub values: u64,
}

/// An upper bound of the values in a JSON text: every value but the first of an array
/// follows a comma, and every array opens with a bracket.
pub fn json_values(json: &[u8]) -> u64 {
    json.iter().filter(|&&b| b == b',' || b == b'[').count() as u64
}

/// The memory a centre gives one upload being read (`[central] max_sync_mb`, in bytes): the
/// decompressed JSON and the values read from it. It sets the [`UploadLimits`] the centre tells
/// every site, and bounds the reading of every upload ([`UploadBudget::read`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UploadBudget {
    /// Bytes of memory.
    pub bytes: usize,
}

/// Memory a JSON value of an upload may take once read, at the most: an `Option<String>` or
/// hex bytes (24 bytes) in a vector that may have doubled.
const BYTES_PER_VALUE: usize = 48;

/// Why an upload's body is not read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum UploadRefusal {
    /// It is, says it is, or would be larger than the budget allows.
    #[error("{0}")]
    TooLarge(String),
    /// It is not what its encoding says.
    #[error("{0}")]
    Malformed(String),
    /// An encoding other than zstd or none.
    #[error("Content-Encoding `{0}`: only zstd or none")]
    Encoding(String),
    /// The decoder could not be set up.
    #[error("zstd decoder: {0}")]
    Decoder(String),
}

impl UploadBudget {
    /// The most a decompressed upload may hold: a quarter of the budget (the buffer may double
    /// while it grows; the values read from it take the other half).
    pub fn max_json_bytes(self) -> usize {
        self.bytes / 4
    }

    /// What the centre reads of one upload at most, told to every site in every answer so
    /// that its batches fit.
    pub fn limits(self) -> UploadLimits {
        UploadLimits {
            json_bytes: self.max_json_bytes() as u64,
            values: (self.bytes / 2 / BYTES_PER_VALUE) as u64,
        }
    }

    /// The zstd window a decoder allows: at most the largest upload, so that a frame cannot
    /// make the decoder allocate more than that.
    fn window_log_max(self) -> u32 {
        let bytes = self.max_json_bytes().max(1 << 20);
        (usize::BITS - (bytes - 1).leading_zeros()).clamp(20, 31)
    }

    /// The JSON of an upload whose body came with `content_encoding` (the header's value,
    /// none for none): decompressed when it is `zstd`, within the budget. The frame's declared
    /// size is checked before anything is allocated, the decoder's window is bounded, and the
    /// decoded text is accepted only when its values fit (counted by their separators).
    pub fn read(
        self,
        content_encoding: Option<&str>,
        body: &[u8],
    ) -> Result<Vec<u8>, UploadRefusal> {
        use std::io::Read;
        let max = self.max_json_bytes();
        let over = |what: &str| {
            UploadRefusal::TooLarge(format!(
                "the upload {what} over {max} bytes once decompressed (a quarter of \
                 `[central] max_sync_mb`)"
            ))
        };
        let json = match content_encoding.map(str::trim) {
            None | Some("identity") => {
                if body.len() > max {
                    return Err(over("is"));
                }
                body.to_vec()
            }
            Some("zstd") => {
                if let Ok(Some(declared)) = zstd::zstd_safe::get_frame_content_size(body)
                    && declared > max as u64
                {
                    return Err(over("says it is"));
                }
                let mut decoder = zstd::stream::read::Decoder::new(body)
                    .map_err(|e| UploadRefusal::Malformed(format!("not zstd: {e}")))?;
                decoder
                    .window_log_max(self.window_log_max())
                    .map_err(|e| UploadRefusal::Decoder(e.to_string()))?;
                let mut out = Vec::new();
                decoder
                    .take(max as u64 + 1)
                    .read_to_end(&mut out)
                    .map_err(|e| {
                        UploadRefusal::Malformed(format!(
                            "the zstd stream is broken or needs too large a window: {e}"
                        ))
                    })?;
                if out.len() > max {
                    return Err(over("is"));
                }
                out
            }
            Some(other) => return Err(UploadRefusal::Encoding(other.to_owned())),
        };
        let values = json_values(&json);
        if values > self.limits().values {
            return Err(UploadRefusal::TooLarge(format!(
                "the upload holds up to {values} values, more than `[central] max_sync_mb` \
                 allows reading at once"
            )));
        }
        Ok(json)
    }
}

/// A site's state as it reports it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SiteStatus {
    /// When the site made the report (its clock, RFC 3339).
    pub time: String,
    /// Its targets.
    pub targets: Vec<TargetStatus>,
    /// What its installation says of its targets (base, paths, thresholds), so that the centre
    /// answers the per-target endpoints of the site's copy with the site's own shapes. Absent
    /// from sites of earlier versions.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub described: Vec<TargetDescription>,
    /// What is wrong at the site that the office must know: the disk budget removed rows
    /// before their time (some never sent).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub problems: Vec<String>,
}

/// A step of a path: a link, taken as stored or inverted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct StepOut {
    /// The link.
    pub link: String,
    /// `forward` (as stored) or `inverted`.
    pub direction: String,
}

/// A path from a target's base to the target.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct PathOut {
    /// Steps from the base outwards.
    pub steps: Vec<StepOut>,
    /// The product it computes, `G_from_C3 * ... * C1_from_B`.
    pub product: String,
    /// The frames it passes, from the base to the target (one more than the steps: step `i`
    /// joins `frames[i]` and `frames[i + 1]`).
    pub frames: Vec<String>,
}

/// A target's deformation thresholds (`null` where not checked): against the magnitude of the
/// deformation's rotation and translation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ThresholdsOut {
    /// Warn at this rotation magnitude (arc-seconds).
    pub warn_rotation_arcsec: Option<f64>,
    /// Alarm at this rotation magnitude (arc-seconds).
    pub alarm_rotation_arcsec: Option<f64>,
    /// Warn at this translation magnitude (mm).
    pub warn_translation_mm: Option<f64>,
    /// Alarm at this translation magnitude (mm).
    pub alarm_translation_mm: Option<f64>,
    /// Alarm at this rate of rotation (arc-seconds per second).
    pub rate_rotation_arcsec_per_s: Option<f64>,
    /// Alarm at this rate of translation (mm per second).
    pub rate_translation_mm_per_s: Option<f64>,
}

impl ThresholdsOut {
    /// The thresholds that judge a deformation's level (hysteresis and dwell are the site's
    /// live alarm state's business, not a single value's).
    pub fn thresholds(&self) -> crate::alarms::AlarmThresholds {
        crate::alarms::AlarmThresholds {
            warn_rotation_arcsec: self.warn_rotation_arcsec,
            alarm_rotation_arcsec: self.alarm_rotation_arcsec,
            warn_translation_mm: self.warn_translation_mm,
            alarm_translation_mm: self.alarm_translation_mm,
            rate_rotation_arcsec_per_s: self.rate_rotation_arcsec_per_s,
            rate_translation_mm_per_s: self.rate_translation_mm_per_s,
            hysteresis: 0.0,
            dwell_s: 0.0,
        }
    }
}

/// What an installation says of one target: its base, how it is reached, its thresholds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct TargetDescription {
    /// Its name (frame).
    pub name: String,
    /// Its base frame.
    pub base: String,
    /// Independent paths (fused).
    pub paths: Vec<PathOut>,
    /// Further paths sharing a link with one above (not fused).
    pub dependent_paths: Vec<PathOut>,
    /// Its alarm thresholds.
    pub alarms: ThresholdsOut,
}

/// The frames a path passes from its base: a forward step `parent_from_child` goes from its
/// child to its parent, an inverted one back.
fn path_frames(topo: &crate::chain::Topology, p: &crate::chain::Path) -> Vec<String> {
    use crate::chain::Direction;
    let mut frames = Vec::with_capacity(p.steps.len() + 1);
    for (i, s) in p.steps.iter().enumerate() {
        let link = topo.link(s.link);
        let (from, to) = match s.direction {
            Direction::Forward => (link.child, link.parent),
            Direction::Inverse => (link.parent, link.child),
        };
        if i == 0 {
            frames.push(topo.frame_name(from).to_owned());
        }
        frames.push(topo.frame_name(to).to_owned());
    }
    frames
}

/// Every target of a model, as its installation describes it, in the installation's order.
pub fn describe_targets(model: &crate::model::Model) -> Vec<TargetDescription> {
    use crate::chain::Direction;
    let topo = &model.topology;
    let path_out = |p: &crate::chain::Path| PathOut {
        frames: path_frames(topo, p),
        steps: p
            .steps
            .iter()
            .map(|s| StepOut {
                link: topo.link(s.link).name.clone(),
                direction: match s.direction {
                    Direction::Forward => "forward",
                    Direction::Inverse => "inverted",
                }
                .to_owned(),
            })
            .collect(),
        product: topo.describe_product(p),
    };
    model
        .targets
        .iter()
        .map(|t| TargetDescription {
            name: t.name.clone(),
            base: topo.frame_name(t.base).to_owned(),
            paths: t.resolution.paths.iter().map(path_out).collect(),
            dependent_paths: t.resolution.dependent_paths.iter().map(path_out).collect(),
            alarms: ThresholdsOut {
                warn_rotation_arcsec: t.alarms.warn_rotation_arcsec,
                alarm_rotation_arcsec: t.alarms.alarm_rotation_arcsec,
                warn_translation_mm: t.alarms.warn_translation_mm,
                alarm_translation_mm: t.alarms.alarm_translation_mm,
                rate_rotation_arcsec_per_s: t.alarms.rate_rotation_arcsec_per_s,
                rate_translation_mm_per_s: t.alarms.rate_translation_mm_per_s,
            },
        })
        .collect()
}

/// One target of a site.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct TargetStatus {
    /// The target.
    pub name: String,
    /// `ok`, `stale`, `degraded`, `initializing` or `predicted` (a word of a site of another
    /// version kept as it came).
    #[schema(value_type = String)]
    pub status: crate::words::Lenient<crate::bank::TargetStatus>,
    /// Its alarm level: `none`, `warn` or `alarm` (likewise).
    #[schema(value_type = String)]
    pub alarm: crate::words::Lenient<crate::alarms::Level>,
    /// The time of its newest result (RFC 3339).
    pub time: Option<String>,
}

/// One tier's backlog as the site reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct TierBacklog {
    /// The tier.
    #[schema(value_type = String)]
    pub tier: Tier,
    /// Rows still to send.
    pub rows: u64,
    /// The last commit the centre acknowledged.
    pub acked_seq: Option<i64>,
    /// Raw tier: rows of the periods the centre asked for still to send (absent from sites of
    /// earlier versions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub requested_rows: Option<u64>,
}

crate::words! {
    /// What became of an upload.
    pub enum Outcome("upload outcome") {
        /// Applied (or a report of state recorded).
        Applied = "applied",
        /// Nothing to apply: the centre has it already.
        Duplicate = "duplicate",
        /// The batch starts after what the centre has: resume from `acked_seq`.
        Gap = "gap",
    }
}

/// The centre's answer.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SyncResponse {
    /// What became of the upload.
    pub outcome: Outcome,
    /// The tier's last applied commit (absent: nothing yet, or a report of state alone).
    pub acked_seq: Option<i64>,
    /// When the site made the commit `acked_seq` (its clock, ns, as the upload that brought
    /// it said; absent: not known). A site whose own commit of that number was made at
    /// another time is another life of the database, whose commits the centre does not hold.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub acked_stamp_ns: Option<i64>,
    /// Periods of raw rows the office asked of this site and has not all of yet.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    #[schema(value_type = Vec<Object>)]
    pub raw_requests: Vec<RawRequest>,
    /// The most the centre reads of one upload (absent from centres of earlier versions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub limits: Option<UploadLimits>,
}

#[cfg(test)]
mod tests {
    use super::*;

    const BUDGET: UploadBudget = UploadBudget { bytes: 4 << 20 };

    /// A JSON array of `n` numbers.
    fn array(n: usize) -> Vec<u8> {
        let mut text = String::from("[");
        text.push_str(&vec!["1"; n].join(","));
        text.push(']');
        text.into_bytes()
    }

    #[test]
    fn an_upload_within_the_budget_reads_back_plain_or_compressed() {
        let json = array(1000);
        assert_eq!(BUDGET.read(None, &json), Ok(json.clone()));
        assert_eq!(BUDGET.read(Some(" identity "), &json), Ok(json.clone()));
        let packed = zstd::bulk::compress(&json, ZSTD_LEVEL).expect("compressed");
        assert_eq!(BUDGET.read(Some("zstd"), &packed), Ok(json));
    }

    #[test]
    fn an_upload_over_the_budget_is_refused_before_it_is_inflated() {
        let max = BUDGET.max_json_bytes();
        assert_eq!(max, 1 << 20);
        let plain = vec![b' '; max + 1];
        assert!(
            matches!(BUDGET.read(None, &plain), Err(UploadRefusal::TooLarge(m)) if m.contains("is over"))
        );
        // A frame that says it inflates past the budget is refused on its word.
        let packed = zstd::bulk::compress(&plain, ZSTD_LEVEL).expect("compressed");
        assert!(packed.len() < 1000, "a bomb: {} bytes", packed.len());
        assert!(
            matches!(BUDGET.read(Some("zstd"), &packed), Err(UploadRefusal::TooLarge(m)) if m.contains("says it is"))
        );
        // A stream that does not say its size (with a window the budget allows: level 1's
        // 512 KiB) is read no further than the budget.
        let mut streamed = Vec::new();
        {
            let mut encoder =
                zstd::stream::write::Encoder::new(&mut streamed, 1).expect("an encoder");
            encoder.include_contentsize(false).expect("set");
            std::io::Write::write_all(&mut encoder, &plain).expect("written");
            encoder.finish().expect("finished");
        }
        assert!(
            matches!(BUDGET.read(Some("zstd"), &streamed), Err(UploadRefusal::TooLarge(m)) if m.contains("is over"))
        );
    }

    #[test]
    fn values_beyond_what_the_budget_reads_are_refused_and_the_limits_say_so() {
        let limits = BUDGET.limits();
        assert_eq!(limits.json_bytes, 1 << 20);
        assert_eq!(limits.values, (2 << 20) / 48);
        let fits = array(limits.values as usize - 1);
        assert!(json_values(&fits) <= limits.values);
        assert!(BUDGET.read(None, &fits).is_ok());
        // Short values: within the bytes, over the values.
        let over = array(limits.values as usize + 1);
        assert!(over.len() <= BUDGET.max_json_bytes());
        assert!(
            matches!(BUDGET.read(None, &over), Err(UploadRefusal::TooLarge(m)) if m.contains("values"))
        );
    }

    #[test]
    fn a_frame_that_needs_a_window_beyond_the_largest_upload_is_refused() {
        // A stream compressor at level 9 asks for an 8 MiB window; this budget's uploads are
        // 1 MiB at most.
        let packed = zstd::encode_all(&array(1000)[..], ZSTD_LEVEL).expect("compressed");
        assert!(
            matches!(BUDGET.read(Some("zstd"), &packed), Err(UploadRefusal::Malformed(m)) if m.contains("window"))
        );
    }

    #[test]
    fn other_encodings_and_broken_streams_are_named() {
        assert_eq!(
            BUDGET.read(Some("gzip"), b"{}"),
            Err(UploadRefusal::Encoding("gzip".into()))
        );
        assert!(matches!(
            BUDGET.read(Some("zstd"), b"{}"),
            Err(UploadRefusal::Malformed(_))
        ));
    }
}
