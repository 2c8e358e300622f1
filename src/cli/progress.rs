//! Progress bars on standard error for the commands that send or read many things.

/// Runs `work` with a bar over frame files on stderr, cleared when it ends.
pub(super) fn with_frames_bar<T>(work: impl FnOnce(&indicatif::ProgressBar) -> T) -> T {
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} frames {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let result = work(&bar);
    bar.finish_and_clear();
    result
}

pub(super) fn progress_bar(groups: Option<u64>) -> indicatif::ProgressBar {
    match groups {
        Some(n) => indicatif::ProgressBar::new(n).with_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:40}] {pos}/{len} groups ({per_sec}, eta {eta})",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        ),
        None => indicatif::ProgressBar::new_spinner().with_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} {elapsed_precise} {pos} groups sent ({per_sec})",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
        ),
    }
}
