//! The tables both schemas share, each described once: its name and its columns with their
//! kinds, in order.
//!
//! Everything that names columns is derived from these descriptions: the column lists of the
//! statements (`sql`), the field counts of PostgreSQL's binary `COPY`, and the columns a site
//! uploads to its centre (`outbox::SyncTable::columns`). Adding a column is an edit here and a
//! migration per backend; the tests of each backend check that the migrated schema and these
//! descriptions agree. SQLite's tables carry one column more, `commit_seq` (the outbox's commit
//! number), which is the site's own and never travels.

/// The type of a column (and of its values on the wire).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// A 64-bit integer.
    Int,
    /// A 64-bit float.
    Real,
    /// UTF-8 text.
    Text,
    /// Bytes.
    Blob,
    /// A boolean (an integer 0 or 1 in SQLite).
    Bool,
}

use Kind::{Blob, Bool, Int, Real, Text};

/// A column: its name and kind.
pub type Column = (&'static str, Kind);

/// A table of both schemas.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Table {
    /// Its name in both schemas.
    pub name: &'static str,
    /// Its columns in order (SQLite's `commit_seq` aside).
    pub columns: &'static [Column],
}

impl Table {
    /// The column names, comma separated, as a statement lists them.
    pub fn list(&self) -> String {
        let names: Vec<&str> = self.columns.iter().map(|(n, _)| *n).collect();
        names.join(", ")
    }

    /// How many columns the table has (a `COPY` row's field count).
    pub fn width(&self) -> usize {
        self.columns.len()
    }
}

/// The columns of a pose, in every table that stores one: translation (mm), then the unit
/// quaternion `w, x, y, z`.
const POSE: [Column; 7] = [
    ("tx_mm", Real),
    ("ty_mm", Real),
    ("tz_mm", Real),
    ("qw", Real),
    ("qx", Real),
    ("qy", Real),
    ("qz", Real),
];

/// A column list with the seven pose columns at `pose`.
macro_rules! columns {
    ($($name:literal : $kind:ident),* ; pose ; $($rest:literal : $rkind:ident),*) => {
        &[$(($name, $kind),)* POSE[0], POSE[1], POSE[2], POSE[3], POSE[4], POSE[5], POSE[6],
          $(($rest, $rkind)),*]
    };
    ($($name:literal : $kind:ident),*) => { &[$(($name, $kind)),*] };
}

/// Measured samples of links.
pub const SAMPLES: Table = Table {
    name: "samples",
    columns: columns!(
        "link_id": Int, "time_ns": Int; pose;
        "uncertainty_kind": Int, "uncertainty": Blob, "reprojection_rms_px": Real,
        "points": Int, "disposition": Text, "outlier": Bool, "nis": Real,
        "received_ns": Int
    ),
};

/// Results of targets, raw (`source` 0) and filtered (1).
pub const RESULTS: Table = Table {
    name: "results",
    columns: columns!(
        "target_id": Int, "source": Int, "time_ns": Int; pose;
        "cov": Blob, "sigma_rx_arcsec": Real, "sigma_ry_arcsec": Real, "sigma_rz_arcsec": Real,
        "sigma_tx_mm": Real, "sigma_ty_mm": Real, "sigma_tz_mm": Real, "status": Text,
        "age_s": Real, "chi2": Real, "reference_version": Int, "def_rx_arcsec": Real,
        "def_ry_arcsec": Real, "def_rz_arcsec": Real, "def_tx_mm": Real, "def_ty_mm": Real,
        "def_tz_mm": Real, "cov_systematic": Blob, "calibration_stamp": Int
    ),
};

/// Alarm transitions and their acknowledgements.
pub const ALARMS: Table = Table {
    name: "alarms",
    columns: columns!(
        "alarm_id": Int, "target_id": Int, "time_ns": Int, "kind": Text,
        "from_level": Text, "to_level": Text, "value": Real, "message": Text,
        "created_ns": Int, "unit": Text, "acknowledged_by": Text,
        "acknowledged_ns": Int, "ack_note": Text
    ),
};

/// Reference versions of targets.
pub const REFERENCES: Table = Table {
    name: "target_references",
    columns: columns!(
        "target_id": Int, "version": Int; pose;
        "cov": Blob, "origin": Text, "window_from_ns": Int, "window_to_ns": Int,
        "window_count": Int, "created_ns": Int, "cov_systematic": Blob, "calibration_stamp": Int
    ),
};

/// Calibration versions of calibrated links.
pub const CALIBRATIONS: Table = Table {
    name: "calibrations",
    columns: columns!(
        "link_id": Int, "version": Int, "valid_from_ns": Int; pose;
        "cov": Blob, "created_ns": Int
    ),
};

/// Manual restarts of links' filters.
pub const LINK_RESETS: Table = Table {
    name: "link_resets",
    columns: columns!("link_id": Int, "created_ns": Int, "by_name": Text, "note": Text),
};

/// Rollups of results: one row a bucket of a level, its statistics in one blob.
pub const ROLLUPS: Table = Table {
    name: "rollups",
    columns: columns!(
        "target_id": Int, "source": Int, "width_s": Int, "bucket_ns": Int, "n": Int,
        "n_def": Int, "stats": Blob
    ),
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_list_names_every_column_once_in_order() {
        assert_eq!(
            LINK_RESETS.list(),
            "link_id, created_ns, by_name, note",
            "the list is the columns in order"
        );
        for table in [
            SAMPLES,
            RESULTS,
            ALARMS,
            REFERENCES,
            CALIBRATIONS,
            LINK_RESETS,
            ROLLUPS,
        ] {
            let list = table.list();
            let names: Vec<&str> = list.split(", ").collect();
            assert_eq!(names.len(), table.width(), "{}", table.name);
            let mut unique = names.clone();
            unique.sort_unstable();
            unique.dedup();
            assert_eq!(unique.len(), names.len(), "{}: a column twice", table.name);
        }
    }
}
