//! Integration tests of the coordinator over real gRPC on loopback, with real SQLite files and
//! local object stores in temporary directories. `stylenerf-testkit` starts the coordinators and
//! provides authenticated clients, test inputs and a fake worker.

mod auth;
mod downloads;
mod hostile;
mod leases;
mod lifecycle;
mod metadata;
mod metrics;
mod priority;
mod progress;
mod quotas;
mod reflection;
mod restart;
mod retention;
mod tls;
mod upload_sessions;
mod uploads;
mod watch_all;
mod web;
mod webhooks;
