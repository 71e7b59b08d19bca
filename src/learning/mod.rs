//! Learning from demonstrations and from the twin (paper §3): datasets, behaviour cloning, the
//! LSTM selector, TD3.

pub mod demos;
