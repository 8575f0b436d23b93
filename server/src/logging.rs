//! Log output: human-readable text or one JSON object per line. Built here (not in main) so
//! that tests check the very subscriber the binary installs.

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
        LogFormat::Text => Box::new(builder.with_ansi(ansi).finish()),
    }
}

/// RUST_LOG, or the default filter.
pub fn env_filter() -> EnvFilter {
    EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(DEFAULT_FILTER))
}
