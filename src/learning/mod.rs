//! Learning from demonstrations and from the twin (paper §3): datasets, behaviour cloning, the
//! LSTM selector, TD3.

pub mod bc;
pub mod dagger;
pub mod dataset;
pub mod demos;
pub mod flat;
pub mod pipeline;
pub mod refine;
pub mod run;
pub mod selector;
pub mod td3;
#[cfg(test)]
mod td3_reach;
