//! The library's error type.

use thiserror::Error;

/// Everything that can go wrong in the library. Messages name the offending value and what
/// would have been valid, so the CLI can print them as they are.
#[derive(Debug, Error)]
pub enum Error {
    /// A backend was asked for that this build does not contain.
    #[error(
        "the {backend} backend is not compiled into this build; rebuild with `--features {feature}`"
    )]
    BackendNotCompiled {
        /// Backend name as the CLI spells it.
        backend: &'static str,
        /// Cargo feature that enables it.
        feature: &'static str,
    },

    /// A compiled backend cannot run on this machine (e.g. wgpu without a usable adapter).
    #[error(
        "the {backend} backend cannot run here: {detail}. wgpu needs a Vulkan, Metal or DX12 \
         driver; without a GPU on Debian/Ubuntu install the software one: \
         `apt-get install mesa-vulkan-drivers libvulkan1`"
    )]
    BackendUnavailable {
        /// Backend name.
        backend: &'static str,
        /// What went wrong.
        detail: String,
    },

    /// The backend cannot compute in the requested precision.
    #[error("the {backend} backend does not support {dtype}")]
    UnsupportedPrecision {
        /// Backend name.
        backend: &'static str,
        /// The precision asked for.
        dtype: &'static str,
    },

    /// A model or solver parameter is out of its valid range.
    #[error("invalid {name} = {value}: must be {expected}")]
    InvalidParameter {
        /// Parameter name (as in SPEC §9 and the CLI).
        name: &'static str,
        /// The rejected value, as written.
        value: String,
        /// The valid range, in words.
        expected: String,
    },

    /// A file could not be read or written.
    // The cause is part of the message and deliberately not a `source()`: the CLI prints
    // error chains, which would repeat it.
    #[error("{}: {cause}", path.display())]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// What the operating system said.
        cause: std::io::Error,
    },

    /// An image file could not be decoded or encoded.
    #[error("{}: {cause}", path.display())]
    Image {
        /// The file.
        path: std::path::PathBuf,
        /// What the decoder said.
        cause: image::ImageError,
    },

    /// An output directory whose outputs would overwrite an input file.
    #[error(
        "the output folder {} holds the input {}, and a run replaces its output folder \
         whole: choose another -o",
        output.display(),
        input.display()
    )]
    Overwrite {
        /// The output directory.
        output: std::path::PathBuf,
        /// The input it would overwrite.
        input: std::path::PathBuf,
    },

    /// An output folder that cannot be used: not a folder, holding files of someone else, or
    /// holding a previous output without `--force`.
    #[error("the output folder {}: {detail}", path.display())]
    OutputFolder {
        /// The folder as given.
        path: std::path::PathBuf,
        /// Why it cannot be used, and what to do.
        detail: String,
    },

    /// A morph would need more memory than it may use.
    #[error(
        "this morph needs about {} ({what}) but {limit_name} is {}: use a smaller --size or \
         --max-side or fewer steps -K{}",
        gib_text(*needed_gib),
        gib_text(*limit_gib),
        if *limit_name == "--max-memory" { ", or raise --max-memory" } else { "" }
    )]
    Memory {
        /// The estimated peak, GiB.
        needed_gib: f64,
        /// The limit, GiB.
        limit_gib: f64,
        /// Where the limit comes from (`--max-memory`, the available memory, `ulimit -v`, the
        /// control group), as the message's subject.
        limit_name: &'static str,
        /// The morph's size, in words.
        what: String,
    },

    /// A NaN or infinity appeared where the solver needs finite numbers.
    #[error("non-finite value: {what}")]
    NonFinite {
        /// Where (level, sweep, step) and which quantity.
        what: String,
    },

    /// A file that could be read but does not hold what it should (truth files, saved
    /// deformations, a morph's output folder).
    #[error("{}: {detail}", path.display())]
    Format {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong with it.
        detail: String,
    },

    /// Tensor arguments whose shapes do not fit together.
    #[error("{op}: {detail}")]
    Shape {
        /// The operation that checked the shapes.
        op: &'static str,
        /// Which shapes, and what was expected.
        detail: String,
    },
}

impl Error {
    /// [`Error::InvalidParameter`] for `name = value`, valid when `expected`.
    pub fn invalid(name: &'static str, value: impl ToString, expected: impl Into<String>) -> Self {
        Self::InvalidParameter {
            name,
            value: value.to_string(),
            expected: expected.into(),
        }
    }
}

/// Shorthand for results of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// A memory size for messages: GiB to one decimal from 1 GiB up, MiB below (a limit of
/// 0.05 GiB is not "0.0 GiB").
fn gib_text(gib: f64) -> String {
    if gib >= 1.0 {
        format!("{gib:.1} GiB")
    } else if gib * 1024.0 >= 1.0 {
        format!("{:.0} MiB", gib * 1024.0)
    } else {
        format!("{:.0} KiB", gib * 1024.0 * 1024.0)
    }
}
