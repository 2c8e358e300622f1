//! The SQLite read side: the queries behind [`crate::store::Store`], by database ids.

use super::super::codec::pose_from_columns;
use super::super::rows::{
    ALARM_COLUMNS, AlarmRow, CALIBRATION_COLUMNS, CalibrationRow, REFERENCE_COLUMNS,
    RESULT_COLUMNS, ReferenceRow, ResultRow, SAMPLE_COLUMNS, SampleRow,
};
use super::super::{StoreError, StoreResult};
use super::Reader;

impl Reader {
    pub(in crate::store) async fn samples(
        &self,
        link_id: i64,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
    ) -> StoreResult<Vec<SampleRow>> {
        Ok(sqlx::query_as(&format!(
            "select {SAMPLE_COLUMNS} from samples where link_id = ? and time_ns >= ? \
             and time_ns <= ? order by time_ns limit ?"
        ))
        .bind(link_id)
        .bind(from_ns)
        .bind(to_ns)
        .bind(limit)
        .fetch_all(&self.pool)
        .await?)
    }

    pub(in crate::store) async fn results(
        &self,
        target_id: i64,
        source: i64,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
    ) -> StoreResult<Vec<ResultRow>> {
        Ok(sqlx::query_as(&format!(
            "select {RESULT_COLUMNS} from results where target_id = ? and source = ? \
             and time_ns >= ? and time_ns <= ? order by time_ns limit ?"
        ))
        .bind(target_id)
        .bind(source)
        .bind(from_ns)
        .bind(to_ns)
        .bind(limit)
        .fetch_all(&self.pool)
        .await?)
    }

    /// Calls `each` with the results in `[from_ns, to_ns]`, oldest first, streamed.
    pub(in crate::store) async fn for_each_result(
        &self,
        target_id: i64,
        source: i64,
        from_ns: i64,
        to_ns: i64,
        mut each: impl FnMut(ResultRow) -> StoreResult<()>,
    ) -> StoreResult<()> {
        use futures::TryStreamExt as _;
        let sql = format!(
            "select {RESULT_COLUMNS} from results where target_id = ? and source = ? \
             and time_ns >= ? and time_ns <= ? order by time_ns"
        );
        let mut rows = sqlx::query_as::<_, ResultRow>(&sql)
            .bind(target_id)
            .bind(source)
            .bind(from_ns)
            .bind(to_ns)
            .fetch(&self.pool);
        while let Some(row) = rows.try_next().await? {
            each(row)?;
        }
        Ok(())
    }

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
            let mut stmt = conn.prepare(
                "select time_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz from results \
                 where target_id = ?1 and source = ?2 and time_ns >= ?3 and time_ns <= ?4 \
                 order by time_ns",
            )?;
            let mut rows = stmt.query(rusqlite::params![target_id, source, from_ns, to_ns])?;
            let mut acc = crate::stats::PoseStatsAccumulator::default();
            let mut span: Option<(i64, i64)> = None;
            while let Some(row) = rows.next()? {
                let t: i64 = row.get(0)?;
                let mut c = [0.0; 7];
                for (i, v) in c.iter_mut().enumerate() {
                    *v = row.get(i + 1)?;
                }
                acc.push(&pose_from_columns(c));
                span = Some((span.map_or(t, |(first, _)| first), t));
            }
            Ok((acc.finish(), span))
        };
        tokio::task::spawn_blocking(scan)
            .await
            .map_err(|e| StoreError::Scan(e.to_string()))?
            .map_err(|e| StoreError::Scan(e.to_string()))
    }

    pub(in crate::store) async fn count_results(
        &self,
        target_id: i64,
        source: i64,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<i64> {
        let (n,): (i64,) = sqlx::query_as(
            "select count(*) from results where target_id = ? and source = ? and time_ns >= ? and time_ns <= ?",
        )
        .bind(target_id)
        .bind(source)
        .bind(from_ns)
        .bind(to_ns)
        .fetch_one(&self.pool)
        .await?;
        Ok(n)
    }

    pub(in crate::store) async fn count_samples(
        &self,
        link_id: i64,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<i64> {
        let (n,): (i64,) = sqlx::query_as(
            "select count(*) from samples where link_id = ? and time_ns >= ? and time_ns <= ?",
        )
        .bind(link_id)
        .bind(from_ns)
        .bind(to_ns)
        .fetch_one(&self.pool)
        .await?;
        Ok(n)
    }

    /// The newest result at or before `at_ns` (`after` false) or the oldest after it.
    pub(in crate::store) async fn result_next_to(
        &self,
        target_id: i64,
        source: i64,
        at_ns: i64,
        after: bool,
    ) -> StoreResult<Option<ResultRow>> {
        let condition = if after {
            "time_ns > ? order by time_ns asc"
        } else {
            "time_ns <= ? order by time_ns desc"
        };
        Ok(sqlx::query_as(&format!(
            "select {RESULT_COLUMNS} from results where target_id = ? and source = ? and {condition} limit 1"
        ))
        .bind(target_id)
        .bind(source)
        .bind(at_ns)
        .fetch_optional(&self.pool)
        .await?)
    }

    pub(in crate::store) async fn references(
        &self,
        target_id: i64,
    ) -> StoreResult<Vec<ReferenceRow>> {
        Ok(sqlx::query_as(&format!(
            "select {REFERENCE_COLUMNS} from target_references where target_id = ? order by version"
        ))
        .bind(target_id)
        .fetch_all(&self.pool)
        .await?)
    }

    pub(in crate::store) async fn calibrations(
        &self,
        link_id: i64,
    ) -> StoreResult<Vec<CalibrationRow>> {
        Ok(sqlx::query_as(&format!(
            "select {CALIBRATION_COLUMNS} from calibrations where link_id = ? order by version"
        ))
        .bind(link_id)
        .fetch_all(&self.pool)
        .await?)
    }

    pub(in crate::store) async fn last_link_resets(
        &self,
    ) -> StoreResult<Vec<(i64, i64, Option<String>, Option<String>)>> {
        Ok(sqlx::query_as(
            "select r.link_id, r.created_ns, r.by_name, r.note from link_resets r \
             where r.created_ns = (select max(created_ns) from link_resets where link_id = r.link_id)",
        )
        .fetch_all(&self.pool)
        .await?)
    }

    pub(in crate::store) async fn filter_state(&self) -> StoreResult<Option<(String, String)>> {
        Ok(
            sqlx::query_as("select installation_digest, state from filter_state where id = 1")
                .fetch_optional(&self.pool)
                .await?,
        )
    }

    pub(in crate::store) async fn alarm(&self, id: i64) -> StoreResult<Option<AlarmRow>> {
        Ok(sqlx::query_as(&format!(
            "select {ALARM_COLUMNS} from alarms where alarm_id = ?"
        ))
        .bind(id)
        .fetch_optional(&self.pool)
        .await?)
    }

    pub(in crate::store) async fn alarms(
        &self,
        target_id: Option<i64>,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
        newest_first: bool,
    ) -> StoreResult<Vec<AlarmRow>> {
        let order = if newest_first {
            "time_ns desc, target_id desc, kind desc"
        } else {
            "time_ns, target_id, kind"
        };
        Ok(sqlx::query_as(&format!(
            "select {ALARM_COLUMNS} from alarms \
             where (? is null or target_id = ?) and time_ns >= ? and time_ns <= ? \
             order by {order} limit ?"
        ))
        .bind(target_id)
        .bind(target_id)
        .bind(from_ns)
        .bind(to_ns)
        .bind(limit)
        .fetch_all(&self.pool)
        .await?)
    }

    /// The level an alarm kind of a target was last left at.
    pub(in crate::store) async fn last_alarm_level(
        &self,
        target_id: i64,
        kind: &str,
    ) -> StoreResult<Option<String>> {
        let row: Option<(String,)> = sqlx::query_as(
            "select to_level from alarms where target_id = ? and kind = ? order by time_ns desc limit 1",
        )
        .bind(target_id)
        .bind(kind)
        .fetch_optional(&self.pool)
        .await?;
        Ok(row.map(|(l,)| l))
    }

    /// The first (`newest` false) or last bucket start of a rollup level.
    pub(in crate::store) async fn rollup_end(
        &self,
        target_id: i64,
        source: i64,
        width_s: i64,
        newest: bool,
    ) -> StoreResult<Option<i64>> {
        // Each end is its own indexed lookup (SQLite optimises a lone `min` or `max`, not both
        // in one query).
        let sql = if newest {
            "select bucket_ns from rollups where target_id = ? and source = ? and width_s = ? order by bucket_ns desc limit 1"
        } else {
            "select bucket_ns from rollups where target_id = ? and source = ? and width_s = ? order by bucket_ns asc limit 1"
        };
        let row: Option<(i64,)> = sqlx::query_as(sql)
            .bind(target_id)
            .bind(source)
            .bind(width_s)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.map(|(b,)| b))
    }

    /// Rollup rows `(start, n, n_def, stats)` of one level with starts in `[from_ns, to_ns]`.
    pub(in crate::store) async fn rollup_rows(
        &self,
        target_id: i64,
        source: i64,
        width_s: i64,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Vec<(i64, i64, i64, Vec<u8>)>> {
        Ok(sqlx::query_as(
            "select bucket_ns, n, n_def, stats from rollups where target_id = ? and source = ? and width_s = ? \
             and bucket_ns >= ? and bucket_ns <= ? order by bucket_ns",
        )
        .bind(target_id)
        .bind(source)
        .bind(width_s)
        .bind(from_ns)
        .bind(to_ns)
        .fetch_all(&self.pool)
        .await?)
    }
}
