//! Shared helpers for himap's cross-crate tests.
