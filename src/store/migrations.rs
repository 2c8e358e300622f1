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
//! compares each list with its folder.

use sqlx::error::BoxDynError;
use sqlx::migrate::{MigrateError, Migration, MigrationSource, MigrationType, Migrator};
use std::borrow::Cow;

/// One folder's migrations: each file's name and text, in order.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Embedded(&'static [(&'static str, &'static str)]);

/// Lists a folder's files, each embedded from the crate's root.
macro_rules! embedded {
    ($folder:literal: $($file:literal),* $(,)?) => {
        Embedded(&[$(($file, include_str!(concat!("../../", $folder, "/", $file)))),*])
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
        self.0
            .iter()
            .map(|&(file, sql)| {
                let (version, rest) = file
                    .split_once('_')
                    .ok_or_else(|| format!("migration {file:?}: no `_` after its version"))?;
                let version: i64 = version
                    .parse()
                    .map_err(|_| format!("migration {file:?}: its version is not an integer"))?;
                let description = rest
                    .strip_suffix(".sql")
                    .ok_or_else(|| format!("migration {file:?}: not a .sql file"))?
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

    /// Every `.sql` file of each folder is listed, in order, with its text.
    #[test]
    fn each_list_is_its_folder() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        for (folder, embedded) in [
            ("migrations", SQLITE),
            ("migrations-postgres", POSTGRES),
            ("migrations-central", CENTRAL),
        ] {
            let mut on_disk: Vec<String> = std::fs::read_dir(root.join(folder))
                .expect("the folder")
                .map(|e| {
                    e.expect("an entry")
                        .file_name()
                        .into_string()
                        .expect("UTF-8")
                })
                .filter(|name| name.ends_with(".sql"))
                .collect();
            on_disk.sort();
            let listed: Vec<&str> = embedded.0.iter().map(|(file, _)| *file).collect();
            assert_eq!(listed, on_disk, "{folder}/ and its list differ");
            for (file, sql) in embedded.0 {
                let text = std::fs::read_to_string(root.join(folder).join(file)).expect("a file");
                assert_eq!(*sql, text, "{folder}/{file}");
            }
        }
    }

    /// Versions, descriptions and checksums as sqlx reads the folders themselves (which is
    /// what the `migrate!` macro embedded): databases migrated before read as up to date.
    #[test]
    fn the_migrations_are_those_sqlx_reads_from_the_folders() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("a runtime");
        for (folder, embedded) in [
            ("migrations", SQLITE),
            ("migrations-postgres", POSTGRES),
            ("migrations-central", CENTRAL),
        ] {
            let ours = embedded.migrations().expect("parsed");
            let theirs = runtime
                .block_on(Migrator::new(root.join(folder)))
                .expect("sqlx reads the folder");
            let theirs: Vec<&Migration> = theirs.iter().collect();
            assert_eq!(ours.len(), theirs.len(), "{folder}");
            for (a, b) in ours.iter().zip(theirs) {
                assert_eq!(a.version, b.version, "{folder}");
                assert_eq!(a.description, b.description, "{folder}");
                assert_eq!(a.checksum, b.checksum, "{folder}");
                assert_eq!(a.no_tx, b.no_tx, "{folder}");
                assert_eq!(a.migration_type, b.migration_type, "{folder}");
            }
        }
    }
}
