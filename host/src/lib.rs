//! himap host library: dataset loaders, synthetic scenes, evaluation metrics, mesh extraction,
//! file outputs and a multi-threaded CPU backend around `himap-core`.

pub mod dataset;
pub mod eval;
pub mod mesh;
pub mod metrics;
pub mod synth;

pub mod atomic;

pub mod backend;
pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod dump;
pub mod geo_init;
pub mod grow;
pub mod lanes;
mod layers;
pub mod mapper_cli;
pub mod planes;
pub mod query;
pub mod select;
pub mod train_demo;
pub mod warp_check;
