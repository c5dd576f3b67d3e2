//! Contour tiles made in-process, one at a time on one thread, as a server with its
//! decoded-tile cache makes them: the tiles of zooms 9 to 13 over an archive's elevation
//! that `scripts/bench-contours.sh` measures (those whose eight neighbours lie over the
//! data too), every 20 m, three rounds. Prints the time a tile, by zoom and in all, and a
//! hash of the bytes (a change that should not change the tiles keeps it).
//!
//! `cargo run --release -p terrastream-views --example contour_time -- x.tspack [rounds]`

use terrastream_format::{LayerKind, Reader};
use terrastream_views::contours::{ContourOptions, contour_tile};
use terrastream_views::mercator::{WebTile, tiles_over};
use terrastream_views::resample::{DECODED_BYTES, DecodedCache};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let path = args.next().ok_or("usage: contour_time ARCHIVE [ROUNDS]")?;
    let rounds: u32 = args.next().map_or(Ok(3), |s| s.parse())?;
    let reader = Reader::open_mmap(&path)?;
    let metadata = reader.metadata();
    let layer = metadata.layers.iter().find(|l| l.kind == LayerKind::Elevation).ok_or("no elevation layer")?;
    let coverage = terrastream_views::tilejson::coverage(metadata, layer, 256)
        .ok_or("the elevation is not placed on the Earth")?;
    let mut tiles = vec![];
    for z in 9..=13u8 {
        let (columns, rows) = tiles_over(z, coverage.bounds);
        let columns = columns.start() + 1..*columns.end();
        for y in rows.start() + 1..*rows.end() {
            tiles.extend(columns.clone().filter_map(|x| WebTile::new(z, x, y)));
        }
    }
    let options = ContourOptions { interval: Some(20.0), major: 5, feet: false };
    let cache = DecodedCache::new(DECODED_BYTES);
    let (mut bytes, mut hash) = (0usize, 0u64);
    // Time and tiles by zoom.
    let mut zooms = [(std::time::Duration::ZERO, 0usize); 14];
    let start = std::time::Instant::now();
    for _ in 0..rounds {
        for &tile in &tiles {
            let began = std::time::Instant::now();
            let made = contour_tile(&reader, tile, options, Some((&cache, 1)))?;
            let zoom = &mut zooms[usize::from(tile.z)];
            (zoom.0, zoom.1) = (zoom.0 + began.elapsed(), zoom.1 + 1);
            if let Some(b) = made {
                bytes += b.len();
                hash = b.iter().fold(hash, |h, &x| h.wrapping_mul(31).wrapping_add(u64::from(x)));
            }
        }
    }
    for (z, (time, count)) in zooms.iter().enumerate().filter(|(_, (_, n))| *n > 0) {
        #[expect(clippy::cast_precision_loss, reason = "a count of tiles")]
        let each = time.as_secs_f64() * 1000.0 / *count as f64;
        println!("zoom {z}: {} tiles, {each:.3} ms a tile", count / rounds as usize);
    }
    let made = tiles.len() * rounds as usize;
    #[expect(clippy::cast_precision_loss, reason = "a count of tiles")]
    let each = start.elapsed().as_secs_f64() * 1000.0 / made as f64;
    println!(
        "{} tiles x {rounds}: {each:.3} ms a tile, {} bytes a round, hash {hash:016x}",
        tiles.len(),
        bytes / rounds as usize
    );
    Ok(())
}
