//! Subcommands of `celld` beyond `eval` and `policy`.

pub mod check;
pub mod latency;
pub mod progress;
pub mod report;
pub mod serve;
pub mod svg;
pub mod train;
pub mod twin_server;
