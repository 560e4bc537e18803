//! Logs of the service's processes (`stylenerf …` and `stylenerf-worker`): a tracing
//! `EnvFilter` and a format, written to stderr. `json` writes one JSON object per line and
//! nothing else; `pretty` colours only a terminal, so logs redirected to a file stay plain.

use std::io::IsTerminal;

/// How log lines look.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines (coloured on a terminal).
    #[default]
    Pretty,
    /// One JSON object per line, for log collectors.
    Json,
}

/// Installs the global subscriber: `filter` in `EnvFilter` syntax (an invalid one falls back to
/// `info`), lines in `format` on stderr.
pub fn init(filter: &str, format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_new(filter)
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Pretty => builder.with_ansi(std::io::stderr().is_terminal()).init(),
        LogFormat::Json => builder.json().init(),
    }
}
