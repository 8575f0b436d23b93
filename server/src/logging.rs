//! Log output: human-readable text or one JSON object per line. Built here (not in main) so
//! that tests check the very subscriber the binary installs.

use tracing_subscriber::field::MakeExt;
use tracing_subscriber::fmt::format::{self, FormatFields};
use tracing_subscriber::fmt::MakeWriter;
use tracing_subscriber::EnvFilter;

use crate::config::LogFormat;

/// Default filter when RUST_LOG is unset.
pub const DEFAULT_FILTER: &str = "info,ort=warn";

/// The subscriber for `format`, writing to `writer`. In JSON, each line carries the current
/// span's fields (request_id, method, path) so log pipelines can group by request.
pub fn subscriber<W>(
    format: LogFormat,
    filter: EnvFilter,
    writer: W,
    ansi: bool,
) -> Box<dyn tracing::Subscriber + Send + Sync>
where
    W: for<'w> MakeWriter<'w> + Send + Sync + 'static,
{
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(writer);
    match format {
        LogFormat::Json => Box::new(builder.json().with_current_span(true).with_span_list(false).finish()),
        LogFormat::Text => Box::new(builder.fmt_fields(escaped_fields()).with_ansi(ansi).finish()),
    }
}

/// The text format's fields (events' and spans'), each with its control characters escaped: a
/// value from outside (a folder's or a manifest's text, a header) cannot end the line and start
/// one that looks like another module's. (JSON escapes them as strings do.)
fn escaped_fields() -> impl for<'w> FormatFields<'w> + Send + Sync + 'static {
    format::debug_fn(|writer, field, value| {
        let text = escape_controls(&format!("{value:?}"));
        match field.name() {
            "message" => write!(writer, "{text}"),
            name => write!(writer, "{name}={text}"),
        }
    })
    .delimited(" ")
}

/// `text` with every control character (and the Unicode line and paragraph separators) written
/// as its Rust escape (`\n`, `\u{1b}`).
pub fn escape_controls(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            c if c.is_control() || c == '\u{2028}' || c == '\u{2029}' => out.extend(c.escape_default()),
            c => out.push(c),
        }
    }
    out
}

/// RUST_LOG, or the default filter.
pub fn env_filter() -> EnvFilter {
    EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(DEFAULT_FILTER))
}

#[cfg(test)]
mod tests {
    use super::escape_controls;

    #[test]
    fn control_characters_are_escaped() {
        assert_eq!(escape_controls("a\nINFO b\r\u{1b}[31m\u{2028}é"), "a\\nINFO b\\r\\u{1b}[31m\\u{2028}é");
    }
}
