//! The stillmap robot client as a library: frame sources ([`source`], [`tum`],
//! `openni`) and their calibration ([`calibration`]), the transport links ([`link`]), the streaming core ([`streamer`]) and
//! trajectory evaluation like evo ([`eval`]).

pub mod bag;
pub mod bench;
pub mod calibration;
pub mod eval;
pub mod fleet;
pub mod link;
#[cfg(feature = "openni2")]
pub mod openni;
pub mod progress;
#[cfg(feature = "zenoh")]
pub mod servers;
pub mod source;
pub mod streamer;
pub mod tum;

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("{0}")]
    Usage(String),
    #[error("source: {0}")]
    Source(String),
    #[error("cannot connect: {0}")]
    Connect(String),
    #[error("server refused: {code:?}: {message}")]
    Server { code: tonic::Code, message: String },
    #[error("protocol: {0}")]
    Protocol(String),
    #[error("{0}")]
    Io(#[from] std::io::Error),
}
