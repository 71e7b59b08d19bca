pub mod cell;
pub mod service;
