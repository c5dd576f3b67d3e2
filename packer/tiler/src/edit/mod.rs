//! Editing archives that exist: merging shards or regions into one archive
//! ([`merge`]), a manifest that names shards where they lie instead ([`manifest`]),
//! tiling a changed region into an archive in place ([`update`]), and what all three
//! share: remaking the tiles an edit leaves stale, the borders and the coarser levels
//! ([`rederive`]).

pub mod manifest;
pub mod merge;
pub mod merged;
pub mod rederive;
pub mod update;
