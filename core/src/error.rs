//! Errors as values: the core never panics on bad sizes or configurations.

/// Everything that can go wrong when building layouts, buffers or a step in the core.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Error {
    /// A fixed capacity would be exceeded: `what` needs `needed`, the capacity is `capacity`.
    Capacity {
        /// What ran out of capacity.
        what: &'static str,
        /// How many elements were needed.
        needed: u64,
        /// How many fit.
        capacity: u64,
    },
    /// A caller-provided buffer has the wrong length.
    Shape {
        /// Which buffer.
        what: &'static str,
        /// The length it must have.
        expected: u64,
        /// The length it has.
        got: u64,
    },
    /// A configuration value is out of its valid range.
    InvalidConfig(&'static str),
}

impl core::fmt::Display for Error {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Error::Capacity {
                what,
                needed,
                capacity,
            } => write!(f, "{what}: needs {needed}, capacity is {capacity}"),
            Error::Shape {
                what,
                expected,
                got,
            } => write!(f, "{what}: expected length {expected}, got {got}"),
            Error::InvalidConfig(msg) => write!(f, "invalid configuration: {msg}"),
        }
    }
}

/// Checks that a buffer has exactly the expected length.
pub fn check_len(what: &'static str, got: usize, expected: usize) -> Result<(), Error> {
    if got == expected {
        Ok(())
    } else {
        Err(Error::Shape {
            what,
            expected: expected as u64,
            got: got as u64,
        })
    }
}

impl core::error::Error for Error {}
