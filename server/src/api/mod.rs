//! The query shells: HTTP (axum) with the dashboard, gRPC `Query`, and the map
//! queries both answer.

pub mod dashboard;
pub mod foxglove;
pub mod http;
pub mod map_queries;
pub mod openapi;
pub mod query;
pub mod serve;
