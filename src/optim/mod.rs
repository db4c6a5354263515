//! The iPALM solver of one level (SPEC §6, the paper's Algorithm 1).

pub mod backtracking;
pub mod ipalm;
pub mod prox;
