//! What a fleet's site uploads: the tiers, the tables in each, and a batch of rows.
//!
//! The site's SQLite file is its outbox (`migrations/0007_outbox.sql`): every write transaction
//! has a commit sequence number and every row carries the number of the transaction that last
//! wrote it (`commit_seq`). A tier's stream is its tables' rows in commit order; the centre
//! acknowledges a tier up to a number, and everything above it is still to send, each row in
//! its current version. A batch covers whole commits `(after_seq, upto_seq]`, so "acknowledged
//! up to N" means every row written by commits up to N has arrived.
//!
//! Rows travel as the site's own columns (column by column, in the order of
//! [`SyncTable::columns`]); the centre writes them into a schema of the same tables, so every
//! read of the store works on a site's copy unchanged.

use serde::{Deserialize, Serialize};

crate::words! {
    /// The tiers of upload, the most urgent first.
    #[derive(PartialOrd, Ord)]
    pub enum Tier("upload tier") {
        /// Alarm transitions (and their acknowledgements), references, calibrations, filter
        /// resets: small, and what an operator ashore must see first.
        Events = "events",
        /// Filtered results and the rollups of all results: the history.
        Results = "results",
        /// Raw samples and raw results: large, sent under a bandwidth budget.
        Raw = "raw",
    }
}

impl Tier {
    /// The tables of the tier's stream.
    pub fn tables(self) -> &'static [SyncTable] {
        match self {
            Tier::Events => &[
                SyncTable::Alarms,
                SyncTable::References,
                SyncTable::Calibrations,
                SyncTable::LinkResets,
            ],
            Tier::Results => &[SyncTable::FilteredResults, SyncTable::Rollups],
            Tier::Raw => &[SyncTable::Samples, SyncTable::RawResults],
        }
    }
}

/// A table (or part of one) that a site uploads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SyncTable {
    /// `alarms`.
    Alarms,
    /// `target_references`.
    References,
    /// `calibrations`.
    Calibrations,
    /// `link_resets`.
    LinkResets,
    /// `results` with source 1.
    FilteredResults,
    /// `rollups`.
    Rollups,
    /// `samples`.
    Samples,
    /// `results` with source 0.
    RawResults,
}

pub use super::schema::Kind;
use super::schema::{self, Table};
use Kind::{Blob, Bool, Int, Real, Text};

impl SyncTable {
    /// The table's name on the wire.
    pub fn name(self) -> &'static str {
        match self {
            SyncTable::Alarms => "alarms",
            SyncTable::References => "references",
            SyncTable::Calibrations => "calibrations",
            SyncTable::LinkResets => "link_resets",
            SyncTable::FilteredResults => "filtered_results",
            SyncTable::Rollups => "rollups",
            SyncTable::Samples => "samples",
            SyncTable::RawResults => "raw_results",
        }
    }

    /// The tier whose stream carries the table.
    pub fn tier(self) -> Tier {
        match self {
            SyncTable::Alarms
            | SyncTable::References
            | SyncTable::Calibrations
            | SyncTable::LinkResets => Tier::Events,
            SyncTable::FilteredResults | SyncTable::Rollups => Tier::Results,
            SyncTable::Samples | SyncTable::RawResults => Tier::Raw,
        }
    }

    /// The table in both schemas (several streams may share one).
    pub fn schema(self) -> Table {
        match self {
            SyncTable::Alarms => schema::ALARMS,
            SyncTable::References => schema::REFERENCES,
            SyncTable::Calibrations => schema::CALIBRATIONS,
            SyncTable::LinkResets => schema::LINK_RESETS,
            SyncTable::FilteredResults | SyncTable::RawResults => schema::RESULTS,
            SyncTable::Rollups => schema::ROLLUPS,
            SyncTable::Samples => schema::SAMPLES,
        }
    }

    /// The table's name in both schemas.
    pub fn table(self) -> &'static str {
        self.schema().name
    }

    /// The rows of the table that belong to this stream (an SQL condition), if not all.
    pub fn filter(self) -> Option<&'static str> {
        match self {
            SyncTable::FilteredResults => Some("source = 1"),
            SyncTable::RawResults => Some("source = 0"),
            _ => None,
        }
    }

    /// The key a row replaces another at.
    pub fn key(self) -> &'static [&'static str] {
        match self {
            SyncTable::Alarms => &["alarm_id"],
            SyncTable::References => &["target_id", "version"],
            SyncTable::Calibrations => &["link_id", "version"],
            SyncTable::LinkResets => &["link_id", "created_ns"],
            SyncTable::FilteredResults | SyncTable::RawResults => {
                &["target_id", "source", "time_ns"]
            }
            SyncTable::Rollups => &["target_id", "source", "width_s", "bucket_ns"],
            SyncTable::Samples => &["link_id", "time_ns"],
        }
    }

    /// The columns that travel, in order, with their types: the table's own.
    pub fn columns(self) -> &'static [(&'static str, Kind)] {
        self.schema().columns
    }

    /// Whether the centre must write the key column of an identity (`alarm_id`).
    pub(crate) fn overrides_identity(self) -> bool {
        self == SyncTable::Alarms
    }
}

/// Bytes that travel as lowercase hex.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HexBytes(pub Vec<u8>);

impl Serialize for HexBytes {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&hex::encode(&self.0))
    }
}

impl<'de> Deserialize<'de> for HexBytes {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = <std::borrow::Cow<'de, str>>::deserialize(d)?;
        hex::decode(text.as_bytes())
            .map(HexBytes)
            .map_err(serde::de::Error::custom)
    }
}

/// One column's values, one a row (`None`: null).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ColumnValues {
    /// Integers.
    Int(Vec<Option<i64>>),
    /// Floating point numbers.
    Real(Vec<Option<f64>>),
    /// Text.
    Text(Vec<Option<String>>),
    /// Byte strings.
    Blob(Vec<Option<HexBytes>>),
    /// Booleans.
    Bool(Vec<Option<bool>>),
}

impl ColumnValues {
    pub(crate) fn empty(kind: Kind) -> ColumnValues {
        match kind {
            Int => ColumnValues::Int(Vec::new()),
            Real => ColumnValues::Real(Vec::new()),
            Text => ColumnValues::Text(Vec::new()),
            Blob => ColumnValues::Blob(Vec::new()),
            Bool => ColumnValues::Bool(Vec::new()),
        }
    }

    /// The type of the values.
    pub(crate) fn kind(&self) -> Kind {
        match self {
            ColumnValues::Int(_) => Int,
            ColumnValues::Real(_) => Real,
            ColumnValues::Text(_) => Text,
            ColumnValues::Blob(_) => Blob,
            ColumnValues::Bool(_) => Bool,
        }
    }

    /// The number of rows.
    pub fn len(&self) -> usize {
        match self {
            ColumnValues::Int(v) => v.len(),
            ColumnValues::Real(v) => v.len(),
            ColumnValues::Text(v) => v.len(),
            ColumnValues::Blob(v) => v.len(),
            ColumnValues::Bool(v) => v.len(),
        }
    }

    /// True without rows.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The rows of one table in a batch, column by column in [`SyncTable::columns`]' order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TableRows {
    /// The table.
    pub table: SyncTable,
    /// Its columns.
    pub columns: Vec<ColumnValues>,
}

impl TableRows {
    pub(crate) fn new(table: SyncTable) -> TableRows {
        TableRows {
            table,
            columns: table
                .columns()
                .iter()
                .map(|(_, kind)| ColumnValues::empty(*kind))
                .collect(),
        }
    }

    /// The number of rows.
    pub fn rows(&self) -> usize {
        self.columns.first().map_or(0, ColumnValues::len)
    }

    /// Why the rows cannot be written, if they cannot: not the table's columns and types, or
    /// columns of different lengths.
    pub fn problem(&self) -> Option<String> {
        let spec = self.table.columns();
        if self.columns.len() != spec.len() {
            return Some(format!(
                "{}: {} columns, the table has {}",
                self.table.name(),
                self.columns.len(),
                spec.len()
            ));
        }
        let rows = self.rows();
        for (values, (name, kind)) in self.columns.iter().zip(spec) {
            if values.kind() != *kind {
                return Some(format!(
                    "{}.{name}: values of the wrong type",
                    self.table.name()
                ));
            }
            if values.len() != rows {
                return Some(format!(
                    "{}.{name}: {} values, the first column has {rows}",
                    self.table.name(),
                    values.len()
                ));
            }
        }
        None
    }
}

/// A site's link or target and its id in the site's database.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Registered {
    /// The id rows refer to.
    pub id: i64,
    /// The link's or target's name.
    pub name: String,
    /// When the site registered it (server clock, ns).
    pub created_ns: i64,
}

/// The names behind the ids of a site's rows.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Registry {
    /// Links.
    pub links: Vec<Registered>,
    /// Targets.
    pub targets: Vec<Registered>,
}

/// The rows of one tier written by the commits `(after_seq, upto_seq]`, or a part of them.
#[derive(Debug, Clone, PartialEq)]
pub struct OutboxBatch {
    /// The tier.
    pub tier: Tier,
    /// The last number the centre acknowledged when the batch was read.
    pub after_seq: i64,
    /// The last commit the batch covers.
    pub upto_seq: i64,
    /// True when the batch holds only a part of the rows of its one commit `upto_seq` (a
    /// commit larger than a batch may be) and more parts follow: the centre applies the rows
    /// but acknowledges nothing new until the last part.
    pub partial: bool,
    /// When the commit `upto_seq` was made (the site's clock, ns; `None` from sites of earlier
    /// versions): with its number it names the commit, so that the centre's acknowledgement
    /// of it can be told from one of another life of the database that reused the number.
    pub upto_stamp_ns: Option<i64>,
    /// The rows, per table (tables without rows left out).
    pub tables: Vec<TableRows>,
}

/// Where the next part of a commit larger than a batch starts: the commit, the table (its
/// place in the tier's list) and the key of the last row already sent from that table.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PartCursor {
    /// The commit.
    pub seq: i64,
    /// The table, as an index into [`Tier::tables`].
    pub table: usize,
    /// The key ([`SyncTable::key`]) of the last row sent from it (`None`: none yet).
    pub after_key: Option<Vec<i64>>,
}

impl OutboxBatch {
    /// The number of rows.
    pub fn rows(&self) -> usize {
        self.tables.iter().map(TableRows::rows).sum()
    }
}

/// Who a site's outbox is: the identity made with its file, and its generation.
///
/// A copy of the file (a backup, restored later) starts a new generation: its next commits
/// reuse numbers the original gave to other rows after the copy was taken, so the centre
/// keeps a stream per generation and takes the copy's as a new one, starting where the copy's
/// acknowledged numbers say.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutboxIdentity {
    /// The outbox (random, made with the file; kept by every copy).
    pub outbox_id: String,
    /// The current generation (the outbox id at first, random in every copy).
    pub generation: String,
    /// The generations it descends from, the nearest first.
    pub lineage: Vec<String>,
}

/// Generations a lineage keeps (the nearest ones): enough for any chain of restores the centre
/// has not seen.
pub const LINEAGE_KEPT: usize = 32;

/// Per tier, what the site has still to send.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Backlog {
    /// The last number the centre acknowledged (`None`: nothing yet).
    pub acked_seq: Option<i64>,
    /// Rows above it.
    pub rows: u64,
}

/// Where the site's retention may not reach: per tier that is uploaded, the last number the
/// centre acknowledged (rows written later are kept whatever their age).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct KeepUnsent {
    /// Filtered results above this number are kept (`None`: the tier is not uploaded).
    pub results: Option<i64>,
    /// Samples and raw results above this number are kept.
    pub raw: Option<i64>,
}

impl KeepUnsent {
    /// What a site keeps given the centre's acknowledgements `acks` (the last number per
    /// tier): filtered results past their tier's, and when raw samples are uploaded
    /// (`raw_uploaded`) samples and raw results past theirs. A tier never acknowledged keeps
    /// everything.
    pub fn from_acks(acks: &[(Tier, i64)], raw_uploaded: bool) -> KeepUnsent {
        let acked = |tier| {
            acks.iter()
                .find(|(t, _)| *t == tier)
                .map_or(i64::MIN, |(_, s)| *s)
        };
        KeepUnsent {
            results: Some(acked(Tier::Results)),
            raw: raw_uploaded.then(|| acked(Tier::Raw)),
        }
    }
}

/// One slice of a period's raw rows (samples and raw results measured in `[from_ns, to_ns)`),
/// as the site has them now: the part of a fleet's upload that answers a [`RawRequest`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RequestedRows {
    /// The centre's request.
    pub request_id: i64,
    /// The slice's start (ns, measurement time).
    pub from_ns: i64,
    /// Its end, excluded.
    pub to_ns: i64,
    /// True when the rows replace those the centre has at their keys (the site's raw tier is
    /// not streamed, so these are its newest versions); false when the raw stream is the
    /// authority on versions and only missing rows are added.
    pub replace: bool,
    /// The rows, per table.
    pub tables: Vec<TableRows>,
}

/// A period of raw rows the centre asks a site for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct RawRequest {
    /// The request.
    pub id: i64,
    /// Its period's start (ns, measurement time).
    pub from_ns: i64,
    /// Its end, excluded.
    pub to_ns: i64,
    /// How far the site has delivered it (from `from_ns`).
    pub delivered_to_ns: i64,
}

#[cfg(test)]
mod tests {
    use super::{KeepUnsent, Tier};

    #[test]
    fn a_site_keeps_what_the_centre_has_not_acknowledged() {
        let acks = [(Tier::Results, 40), (Tier::Raw, 7), (Tier::Events, 99)];
        assert_eq!(
            KeepUnsent::from_acks(&acks, true),
            KeepUnsent {
                results: Some(40),
                raw: Some(7)
            }
        );
        assert_eq!(
            KeepUnsent::from_acks(&acks, false),
            KeepUnsent {
                results: Some(40),
                raw: None
            },
            "raw rows not uploaded are not held back"
        );
        assert_eq!(
            KeepUnsent::from_acks(&[], true),
            KeepUnsent {
                results: Some(i64::MIN),
                raw: Some(i64::MIN)
            },
            "a tier never acknowledged keeps everything"
        );
    }
}
