//! One module per family of subcommands; `main` dispatches to them.

pub(crate) mod bench;
pub(crate) mod daemons;
pub(crate) mod radiosity;
pub(crate) mod radiosity_farm;
pub(crate) mod render;
pub(crate) mod tools;
