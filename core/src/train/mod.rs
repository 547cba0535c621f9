//! Training: how one step changes the field, identically on every backend.
//!
//! - [`backend`]: the [`Backend`](backend::Backend) trait the mapper and the CLI drive, and
//!   what every backend shares (batches, the image store, step statistics);
//! - [`reference`](mod@reference): the single-threaded reference backend every other one must
//!   match bit for bit;
//! - [`batch`]: the CPU backends' batch driver (what one ray or pixel item runs);
//! - [`pixel`]: the per-pixel mapping kernel (colour and warping losses of one window pixel);
//! - [`fixed`]: the fixed-point gradient accumulation that makes sums order-independent;
//! - [`adam`]: the optimiser, per parameter.

pub mod adam;
pub mod backend;
pub mod batch;
pub mod fixed;
pub mod pixel;
pub mod reference;
