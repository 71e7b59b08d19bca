pub mod cell;
pub mod drivers;
pub mod service;
