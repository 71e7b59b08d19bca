pub mod cell;
pub mod drivers;
pub mod fixture_layout;
pub mod service;
