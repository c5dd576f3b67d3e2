//! Exporting a layer to another tile-archive format.

pub mod pmtiles;
