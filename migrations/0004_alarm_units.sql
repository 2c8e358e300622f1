-- The unit of an alarm transition's deciding value: arcsec or mm (deformation), arcsec_per_s
-- or mm_per_s (rate), none (stale). The value is the rotation or the translation, whichever
-- is the larger fraction of its threshold. Older rows (null) held the rotation.
alter table alarms add column unit text;
