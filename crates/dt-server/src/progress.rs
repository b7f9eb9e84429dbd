//! Progress bars for long commands: drawn on a terminal's stderr, hidden
//! when stderr is not a terminal or `CI` is set (CI logs stay quiet).

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// A bar of `len` steps named `what` (hidden off a terminal and in CI).
#[must_use]
pub fn bar(len: u64, what: &str) -> ProgressBar {
    let ci = std::env::var_os("CI").is_some_and(|v| !v.is_empty());
    let target = if ci {
        ProgressDrawTarget::hidden()
    } else {
        ProgressDrawTarget::stderr()
    };
    let bar = ProgressBar::with_draw_target(Some(len), target);
    if let Ok(style) =
        ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg} ({elapsed}, eta {eta})")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_prefix(what.to_owned());
    bar
}
