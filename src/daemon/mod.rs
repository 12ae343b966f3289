//! The daemon: `glint daemon` holds the rig's devices, runs capture-and-fit jobs from a
//! queue one at a time, and streams their progress to clients over a Unix socket.
//!
//! It is a thin shell over the same engine and pipeline `glint run` uses: a job is data
//! (the options `glint run` takes, [`protocol::JobSpec`]), run by
//! [`crate::pipeline::run_returning`] on a blocking thread; the daemon adds only the socket
//! and its protocol ([`protocol`], [`server`]), the queue and its journal ([`journal`]), the
//! fan-out of events ([`hub`]), and the hands an operator lends through a client
//! ([`runner`]). What must survive a crash (the queue, the history, which job was running)
//! is on disk before it is acted on; after a crash nothing switches the lamp on until
//! someone says so (`glint queue start`).
//!
//! tokio serves the socket and the event fan-out only; the numerics stay synchronous.
//! Clients ([`client`]) are plain blocking code.

pub mod client;
pub mod hub;
pub mod journal;
pub mod paths;
pub mod protocol;
pub mod runner;
pub mod server;

pub use runner::OperatorMode;
pub use server::{serve, Options};
