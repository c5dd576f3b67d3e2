//! Writing terrastream archives (`*.tspack`): the streaming [`Writer`], the importers
//! behind `terrastream pack` (original LOD folders, XYZ/TMS trees, PMTiles, MBTiles),
//! [`extract`](extract::extract) back to folders, exporters to other formats, the
//! built-in [`sample`] terrain (and [`sample::TAMALPAIS_TIF`], a real DEM crop), and the
//! [`labelled`] archives that benchmarks stream. Reading is `terrastream-format`'s.

mod append;
mod compress;
mod error;
pub mod export;
pub mod extract;
pub mod import;
pub mod labelled;
pub mod progress;
mod publish;
pub mod sample;
mod writer;

pub use append::Appender;
pub use compress::{compress_heights, zstd_compress, zstd_compress_gradient, zstd_compress_samples};
pub use error::{Error, Result};
pub use publish::output_folder;
pub use terrastream_format::Interrupted;
pub use writer::{BOOTSTRAP_SLOT, DatumOver, WriteSummary, Writer, WriterOptions, record_extents};
