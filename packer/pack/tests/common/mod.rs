//! Helpers shared by the packer's integration tests.
#![allow(dead_code, missing_docs, clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use terrastream_format::{Layer, LayerKind, Metadata, PayloadCompression, TileFormat};

pub fn layer(name: &str, nx: u32, ny: u32, num_lods: u8) -> Layer {
    Layer {
        name: name.into(),
        kind: if name.starts_with("elev") { LayerKind::Elevation } else { LayerKind::Texture },
        format: TileFormat::Png,
        compression: PayloadCompression::None,
        tile_resolution: 256,
        border: 0,
        num_x_tiles: nx,
        num_y_tiles: ny,
        num_lods,
        tile_world_size: 100.0,
        elevation: None,
        extent: None,
    }
}

pub fn metadata(layers: Vec<Layer>) -> Metadata {
    Metadata::new("test", layers)
}

/// Every file under `dir` as (relative path, bytes), sorted.
pub fn tree(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((p.strip_prefix(dir).unwrap().to_path_buf(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

/// Minimal executor for the async reader: sources that are ready at once.
pub fn block_on<F: Future>(f: F) -> F::Output {
    let mut f = std::pin::pin!(f);
    let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
    loop {
        if let std::task::Poll::Ready(v) = f.as_mut().poll(&mut cx) {
            return v;
        }
    }
}
