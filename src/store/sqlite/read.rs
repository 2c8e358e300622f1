//! The SQLite read side that differs from PostgreSQL's: the statistics of a window, folded on
//! a connection of rusqlite's.

use super::super::codec::{pose_from_columns, random_covariance};
use super::super::{StoreError, StoreResult};
use super::Reader;

impl Reader {
    /// The paper's statistics of a target's results in `[from_ns, to_ns]` and the span they
    /// cover. The rows are streamed and folded one by one on a blocking thread, through a
    /// read-only rusqlite connection of its own (the pool's driver costs several microseconds
    /// a row, which over millions of results is many seconds): memory does not grow with the
    /// window.
    pub(in crate::store) async fn pose_stats(
        &self,
        target_id: i64,
        source: i64,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<(Option<crate::stats::PoseStats>, Option<(i64, i64)>)> {
        let path = self.path.clone();
        let scan = move || -> rusqlite::Result<_> {
            use rusqlite::OpenFlags;
            let conn = rusqlite::Connection::open_with_flags(
                &path,
                OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
            )?;
            conn.busy_timeout(std::time::Duration::from_secs(10))?;
            let mut stmt = conn.prepare(super::super::sql::RESULT_POSES_IN)?;
            let mut rows = stmt.query(rusqlite::params![target_id, source, from_ns, to_ns])?;
            let mut acc = crate::stats::PoseStatsAccumulator::default();
            let mut span: Option<(i64, i64)> = None;
            while let Some(row) = rows.next()? {
                let t: i64 = row.get(0)?;
                let mut c = [0.0; 7];
                for (i, v) in c.iter_mut().enumerate() {
                    *v = row.get(i + 1)?;
                }
                let cov: Vec<u8> = row.get(8)?;
                let systematic: Option<Vec<u8>> = row.get(9)?;
                let pose = pose_from_columns(c);
                match random_covariance(&cov, systematic.as_deref()) {
                    Some(random) => acc.push_with_random(&pose, &random),
                    None => acc.push(&pose),
                }
                span = Some((span.map_or(t, |(first, _)| first), t));
            }
            Ok((acc.finish(), span))
        };
        tokio::task::spawn_blocking(scan)
            .await
            .map_err(|e| StoreError::Scan(e.to_string()))?
            .map_err(|e| StoreError::Scan(e.to_string()))
    }
}
