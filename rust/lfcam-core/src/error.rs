//! The error type of every fallible function in the core.

/// Everything that can go wrong in a core function.
///
/// The Python bindings map each variant to a class of the `lfcam.errors` family
/// (`InvalidArgument` and `InvalidItem` to `InputError`, a `ValueError`; `Internal` to
/// the family's base class `LfcamError`, since the caller is not at fault). New
/// variants may be added: the enum is `#[non_exhaustive]`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// An argument is unusable as a whole (wrong size, empty, out of range).
    #[error("{arg}: {reason}")]
    InvalidArgument {
        /// The argument's name, as the caller spelled it.
        arg: String,
        /// What is wrong with it, phrased to follow `"{arg}: "`.
        reason: String,
    },
    /// One element of a sequence argument is unusable (e.g. one crop rectangle).
    #[error("{arg}[{index}]: {reason}")]
    InvalidItem {
        /// The sequence argument's name.
        arg: String,
        /// The zero-based index of the offending element.
        index: usize,
        /// What is wrong with it.
        reason: String,
    },
    /// A numerical procedure failed (singular system, no convergence, non-finite result).
    #[error("{0}")]
    Numerical(String),
    /// An invariant of lfcam itself is broken: a bug, never the caller's fault (for
    /// example a size the function checked on entry disagreeing later).
    #[error("internal error in {function}: {detail}; please report this")]
    Internal {
        /// The public function that found it.
        function: &'static str,
        /// What was found.
        detail: String,
    },
}

impl Error {
    /// Builds [`Error::InvalidArgument`].
    pub fn invalid_argument(arg: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::InvalidArgument {
            arg: arg.into(),
            reason: reason.into(),
        }
    }

    /// Builds [`Error::Internal`].
    pub fn internal(function: &'static str, detail: impl Into<String>) -> Self {
        Self::Internal {
            function,
            detail: detail.into(),
        }
    }

    /// Builds [`Error::InvalidItem`].
    pub fn invalid_item(arg: impl Into<String>, index: usize, reason: impl Into<String>) -> Self {
        Self::InvalidItem {
            arg: arg.into(),
            index,
            reason: reason.into(),
        }
    }
}

/// `Result` with the core [`Error`].
pub type Result<T> = std::result::Result<T, Error>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_name_the_argument() {
        assert_eq!(
            Error::invalid_argument("raw", "must not be empty").to_string(),
            "raw: must not be empty"
        );
        assert_eq!(
            Error::invalid_item("rects", 3, "outside the frame").to_string(),
            "rects[3]: outside the frame"
        );
        assert_eq!(
            Error::internal("rectify", "row 3").to_string(),
            "internal error in rectify: row 3; please report this"
        );
        assert_eq!(Error::Numerical("singular".into()).to_string(), "singular");
    }
}
