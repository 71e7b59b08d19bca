//! Subcommands of `celld` beyond `eval` and `policy`.

pub mod train;
