//! The `celld` command line run as a user runs it: eval, policy, train and the driver
//! commands, their output and their refusals.

#[path = "../support/common.rs"]
mod common;

mod cli_drivers;
mod cli_eval;
mod cli_policy;
mod cli_train;
