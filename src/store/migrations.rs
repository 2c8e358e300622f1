//! The schemas' migrations, embedded in the binary: SQLite's (`migrations/`), PostgreSQL's
//! (`migrations-postgres/`) and a fleet centre's own (`migrations-central/`).
//!
//! Each folder's files are listed here by name and read with `include_str!`, and handed to
//! sqlx's migrator as its source. The migrator computes each file's checksum from its text and
//! refuses a database whose applied migrations have changed, as it did when the folders were
//! embedded by sqlx's `migrate!` macro: the versions, descriptions and checksums are the same,
//! so databases migrated by either read as up to date. (The macro compiled a second copy of
//! sqlx and both database drivers for the compiler's host, a minute of every cold build.)
//!
//! A file added to a folder and not to its list would never be applied: the unit test below
//! compares each list with its folder as sqlx reads it.

use sqlx::error::BoxDynError;
use sqlx::migrate::{MigrateError, Migration, MigrationSource, MigrationType, Migrator};
use std::borrow::Cow;

/// One folder's migrations: the folder (from the crate's root) and each file's name and text,
/// in order.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Embedded {
    folder: &'static str,
    files: &'static [(&'static str, &'static str)],
}

/// Lists a folder's files, each embedded from the crate's root.
macro_rules! embedded {
    ($folder:literal: $($file:literal),* $(,)?) => {
        Embedded {
            folder: $folder,
            files: &[$(($file, include_str!(concat!("../../", $folder, "/", $file)))),*],
        }
    };
}

/// SQLite's migrations (`migrations/`).
pub(crate) const SQLITE: Embedded = embedded!("migrations":
    "0001_initial.sql",
    "0002_rollups.sql",
    "0003_alarms.sql",
    "0004_alarm_units.sql",
    "0005_link_resets.sql",
    "0006_alarm_ids_and_acks.sql",
    "0007_outbox.sql",
    "0008_outbox_generation.sql",
    "0009_systematic_covariance.sql",
    "0010_acceptances.sql",
);

/// PostgreSQL's migrations (`migrations-postgres/`): a site's schema, at a site or in a
/// centre.
pub(crate) const POSTGRES: Embedded = embedded!("migrations-postgres":
    "0001_initial.sql",
    "0002_systematic_covariance.sql",
    "0003_acceptances.sql",
);

/// A fleet centre's own migrations (`migrations-central/`), in the schema `fleet`.
pub(crate) const CENTRAL: Embedded = embedded!("migrations-central":
    "0001_fleet.sql",
    "0002_raw_requests.sql",
    "0003_generations.sql",
    "0004_raw_request_cancel.sql",
    "0005_acked_stamp.sql",
);

impl Embedded {
    /// Applies those of these migrations that `conn`'s database lacks, as sqlx's migrator does
    /// by default: each in its own transaction, the database locked while migrating, and a
    /// database refused that has one applied that is not listed or was changed since.
    pub(crate) async fn run<'a, A>(self, conn: A) -> Result<(), MigrateError>
    where
        A: sqlx::Acquire<'a>,
        <A::Connection as std::ops::Deref>::Target: sqlx::migrate::Migrate,
    {
        Migrator::new(self).await?.run(conn).await
    }

    /// The migrations, named and parsed as sqlx parses a folder's files:
    /// `<version>_<description>.sql`, the description's underscores read as spaces, and a file
    /// whose text starts with `-- no-transaction` run outside a transaction.
    fn migrations(self) -> Result<Vec<Migration>, String> {
        self.files
            .iter()
            .map(|&(file, sql)| {
                let (version, rest) = file.split_once('_').ok_or_else(|| {
                    format!("migration {}/{file}: no `_` after its version", self.folder)
                })?;
                let version: i64 = version.parse().map_err(|_| {
                    format!(
                        "migration {}/{file}: its version is not an integer",
                        self.folder
                    )
                })?;
                let description = rest
                    .strip_suffix(".sql")
                    .ok_or_else(|| format!("migration {}/{file}: not a .sql file", self.folder))?
                    .replace('_', " ");
                Ok(Migration::new(
                    version,
                    Cow::Owned(description),
                    MigrationType::from_filename(rest),
                    Cow::Borrowed(sql),
                    sql.starts_with("-- no-transaction"),
                ))
            })
            .collect()
    }
}

impl<'s> MigrationSource<'s> for Embedded {
    fn resolve(self) -> futures::future::BoxFuture<'s, Result<Vec<Migration>, BoxDynError>> {
        Box::pin(async move { self.migrations().map_err(BoxDynError::from) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each list is its folder, and each migration's version, description, checksum (its
    /// text) and kind are what sqlx reads from the folder itself, which is what the `migrate!`
    /// macro embedded: a file left out of a list fails here, and databases migrated before
    /// read as up to date.
    #[test]
    fn each_list_is_its_folder_as_sqlx_reads_it() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("a runtime");
        for embedded in [SQLITE, POSTGRES, CENTRAL] {
            let folder = embedded.folder;
            let ours = embedded.migrations().expect("parsed");
            let theirs = runtime
                .block_on(Migrator::new(root.join(folder)))
                .expect("sqlx reads the folder");
            let versions = |m: &mut dyn Iterator<Item = &Migration>| -> Vec<i64> {
                m.map(|m| m.version).collect()
            };
            assert_eq!(
                versions(&mut ours.iter()),
                versions(&mut theirs.iter()),
                "{folder}/ and its list in store::migrations differ"
            );
            for (a, b) in ours.iter().zip(theirs.iter()) {
                let which = format!("{folder}/ version {}", a.version);
                assert_eq!(a.description, b.description, "{which}");
                assert_eq!(a.checksum, b.checksum, "{which}");
                assert_eq!(a.no_tx, b.no_tx, "{which}");
                assert_eq!(a.migration_type, b.migration_type, "{which}");
            }
        }
    }
}
